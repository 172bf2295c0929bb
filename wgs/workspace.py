"""The workspace contract: numbered stage folders, manifests, atomic writes, a lock, freshness.

Layout::

    WS/scene/  1_coarse/  2_mask_data/  3_finetune/  4_repair/  5_fine/  6_eval/
    WS/<stage>/manifest.json   resolved config, fingerprint, upstream fingerprints, times, status

A stage writes into a staging folder (WS/.resume/<stage>/out/) and is swapped in by rename only
when it succeeded, so an interrupted or failed stage leaves the last good output untouched; with
--resume an interrupted stage continues from that folder and its loops' saved states.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import resource
import shutil
import socket
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__
from .config import as_dict
from .errors import InputError, WgsError, WorkspaceLocked
from .io import atomic_write_bytes, atomic_write_json, json_default, path_in
from .resume import Checkpointer
from .stages.registry import REGISTRY, STAGE

STAGE_DIRS: dict[str, str] = {s.name: s.folder for s in REGISTRY}
UPSTREAM: dict[str, tuple[str, ...]] = {s.name: s.upstream for s in REGISTRY}
MANIFEST = "manifest.json"
LOCK = ".wgs.lock"
RUN_RECORD = "run.json"  # the last `wgs all` or `wgs prepare`'s calibration, estimate and budget plan (wgs.estimate)
RESUME = ".resume"  # WS/.resume/<stage dir>/: staging folder `out/`, loop checkpoints `*.pt`, `fingerprint`


def declared(stage: str, key: str) -> str:
    """The path, inside its folder, of the output `key` that `stage` declares in the registry."""
    try:
        return STAGE[stage].outputs[key]
    except KeyError:
        raise KeyError(f"stage {stage!r} declares no output {key!r} (stages.registry)") from None


def fingerprint(obj: Any) -> str:
    """Stable sha256 of a JSON-able object (config + upstream fingerprints + version)."""
    blob = json.dumps(obj, sort_keys=True, default=json_default).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / 2**20


# ----------------------------------------------------------------------------- the workspace
@dataclass
class StageRun:
    """A stage in progress: write outputs under `dir`; `record` goes into the manifest; long loops
    save their state through `checkpointer(key)`."""

    stage: str
    dir: Path
    record: dict[str, Any] = field(default_factory=dict)
    resume: bool = False
    checkpoint_every: float = 60.0

    def path(self, *parts: str) -> Path:
        return path_in(self.dir, *parts)

    def output(self, key: str, *parts: str) -> Path:
        """Where this stage writes its declared output `key` (`config.Stage.outputs`), parent created."""
        return path_in(self.dir, declared(self.stage, key), *parts)

    def checkpointer(self, key: str) -> Checkpointer:
        return Checkpointer(self.dir.parent / f"{key}.pt", self.checkpoint_every, self.resume)


class Workspace:
    """resume: continue interrupted stages from their saved state; checkpoint_every: seconds
    between state saves inside long loops."""

    def __init__(self, root: str | Path, resume: bool = False, checkpoint_every: float = 60.0):
        self.root = Path(root)
        self.resume = resume
        self.checkpoint_every = checkpoint_every

    def __repr__(self) -> str:
        return f"Workspace({str(self.root)!r})"

    def stage_dir(self, stage: str) -> Path:
        return self.root / STAGE_DIRS[stage]

    def output(self, stage: str, key: str, *parts: str) -> Path:
        """A file or folder that `stage` declares as its output `key` (`config.Stage.outputs`)."""
        return self.stage_dir(stage).joinpath(declared(stage, key), *parts)

    def run_record(self) -> dict[str, Any]:
        """What the last run planned (`RUN_RECORD`): {} when none did."""
        try:
            data = json.loads((self.root / RUN_RECORD).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError, UnicodeDecodeError):
            return {}
        return data if isinstance(data, dict) else {}

    def write_run_record(self, record: dict[str, Any]) -> None:
        atomic_write_json(self.root / RUN_RECORD, record)

    def resume_dir(self, stage: str) -> Path:
        return self.root / RESUME / STAGE_DIRS[stage]

    def manifest(self, stage: str) -> dict[str, Any] | None:
        """The stage's manifest when it finished successfully, else None."""
        path = self.stage_dir(stage) / MANIFEST
        if not path.exists():
            return None
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError, OSError):
            return None
        return data if isinstance(data, dict) and data.get("status") == "done" else None

    def finished(self, stage: str) -> dict[str, Any]:
        """The manifest of a stage that must have finished (InputError naming its folder otherwise)."""
        m = self.manifest(stage)
        if m is None:
            raise InputError(f"the {stage} stage has not finished here", self.stage_dir(stage))
        return m

    def upstream_fingerprints(self, stage: str) -> dict[str, str | None]:
        out: dict[str, str | None] = {}
        for up in UPSTREAM[stage]:
            m = self.manifest(up)
            out[up] = None if m is None else m.get("fingerprint")
        return out

    def stage_fingerprint(self, stage: str, config: dict[str, Any], extra: Any = None) -> str:
        return fingerprint(
            {
                "stage": stage,
                "config": config,
                "upstream": self.upstream_fingerprints(stage),
                "extra": extra,
                "version": __version__,
            }
        )

    def status(self, stage: str, fp: str | None = None) -> str:
        """'missing', 'stale' (inputs or config changed) or 'fresh'."""
        m = self.manifest(stage)
        if m is None:
            return "missing"
        if m.get("upstream") != self.upstream_fingerprints(stage):
            return "stale"
        if fp is not None and m.get("fingerprint") != fp:
            return "stale"
        return "fresh"

    def begin(
        self, stage: str, config: dict[str, Any], extra: Any = None, force: bool = False, requires: tuple[str, ...] = ()
    ) -> str | None:
        """Call under the lock: the fingerprint to run the stage with, or None when it is fresh."""
        from .progress import log

        fp = self.stage_fingerprint(stage, config, extra)
        if not force and self.status(stage, fp) == "fresh":
            log(f"{STAGE[stage].command}: up to date, skipped")
            return None
        for req in requires:
            if self.manifest(req) is None:
                raise InputError(
                    f"the {STAGE[req].command} stage has not run: run `wgs {STAGE[req].command}` first",
                    self.stage_dir(req),
                )
        return fp

    # -- locking -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive write access; a lock left by a dead process on this host is taken over."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise WgsError(f"cannot create the workspace folder ({exc.strerror})", self.root) from None
        path = self.root / LOCK
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        for _ in range(3):
            try:
                fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = _read_lock(path)
                if holder is not None and _lock_alive(holder):
                    raise WorkspaceLocked(
                        f"workspace is in use by pid {holder.get('pid')} on {holder.get('host')} "
                        f"since {holder.get('started')}",
                        self.root,
                    ) from None
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()  # stale lock from a dead process
                continue
            except OSError as exc:
                if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                    raise WgsError(f"the workspace is not writable ({exc.strerror})", self.root) from None
                raise
            with os.fdopen(fd, "w") as fh:
                json.dump(me, fh)
            break
        else:
            raise WorkspaceLocked("could not take the workspace lock", self.root)
        try:
            self._recover()
            yield
        finally:
            with contextlib.suppress(FileNotFoundError):
                if (_read_lock(path) or {}).get("pid") == me["pid"]:
                    path.unlink()

    def _recover(self) -> None:
        """Undo what an interrupted swap or stage left behind."""
        for name in STAGE_DIRS.values():
            final = self.root / name
            for old in self.root.glob(f".{name}.old-*"):
                if not final.exists():
                    old.rename(final)
                else:
                    shutil.rmtree(old, ignore_errors=True)
            for tmp in self.root.glob(f".{name}.tmp-*"):
                shutil.rmtree(tmp, ignore_errors=True)
        for stage in STAGE_DIRS:  # killed after the swap, before the clean-up
            m = self.manifest(stage)
            if m is not None and _read_text(self.resume_dir(stage) / "fingerprint") == m.get("fingerprint"):
                self._drop_resume(stage)

    def _drop_resume(self, stage: str) -> None:
        shutil.rmtree(self.resume_dir(stage), ignore_errors=True)
        with contextlib.suppress(OSError):
            self.resume_dir(stage).parent.rmdir()  # only when empty

    def _drop_unresumable(self, stage: str) -> None:
        """A failed stage keeps its folder under .resume/ only when a loop saved its state there."""
        rdir = self.resume_dir(stage)
        if not any(rdir.glob("*.pt")):
            self._drop_resume(stage)

    def _prepare_resume(self, stage: str, fp: str) -> Path:
        """The staging folder: kept from an interrupted run of the same fingerprint with --resume,
        else emptied."""
        from .progress import log

        rdir = self.resume_dir(stage)
        old = _read_text(rdir / "fingerprint")
        if rdir.exists():
            if self.resume and old == fp:
                saved = any(rdir.glob("*.pt"))
                log(
                    f"{STAGE[stage].command}: resuming "
                    + ("from the saved state" if saved else "(keeping the files written before the interruption)")
                )
                (rdir / "out").mkdir(parents=True, exist_ok=True)
                return rdir / "out"
            if not self.resume and any(rdir.glob("*.pt")):
                log(f"{STAGE[stage].command}: starting over (add --resume to continue from the saved state)")
            elif self.resume:
                log(f"{STAGE[stage].command}: the saved state belongs to other inputs or settings: starting over")
            shutil.rmtree(rdir)
        (rdir / "out").mkdir(parents=True)
        atomic_write_bytes(rdir / "fingerprint", fp.encode())
        return rdir / "out"

    # -- running a stage -------------------------------------------------------------------------
    def run_staged(
        self,
        stage: str,
        settings: Any,
        extra: Any,
        force: bool,
        body: Callable[[StageRun], str],
        requires: tuple[str, ...] | None = None,
    ) -> bool:
        """Every stage's runner: under the lock, skip the stage when it is fresh, check that the stages
        it reads have run (`requires`, default its registry upstream), run body(run) in the staging
        folder and swap it in with the manifest; body returns the line to log. Returns False when
        the stage was up to date."""
        from .progress import log

        config = as_dict(settings)
        with self.lock():
            fp = self.begin(stage, config, extra, force, UPSTREAM[stage] if requires is None else requires)
            if fp is None:
                return False
            with self.stage_run(stage, config, fp) as run:
                message = body(run)
        log(message)
        return True

    @contextlib.contextmanager
    def stage_run(self, stage: str, config: dict[str, Any], fp: str) -> Iterator[StageRun]:
        """Stage outputs go to a staging folder, swapped in with the manifest only on success."""
        name = STAGE_DIRS[stage]
        staging = self._prepare_resume(stage, fp)
        run = StageRun(stage, staging, resume=self.resume, checkpoint_every=self.checkpoint_every)
        t0 = time.perf_counter()
        try:
            yield run
        except Exception:
            self._drop_unresumable(stage)
            raise
        # on Ctrl-C (KeyboardInterrupt) or SIGKILL the staging folder stays for --resume
        manifest = {
            "stage": stage,
            "status": "done",
            "fingerprint": fp,
            "upstream": self.upstream_fingerprints(stage),
            "config": config,
            "version": __version__,
            "wall_time_s": round(time.perf_counter() - t0, 3),
            "peak_memory_mb": round(peak_memory_mb(), 1),
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
            **run.record,
        }
        atomic_write_json(staging / MANIFEST, manifest)
        final = self.root / name
        old = self.root / f".{name}.old-{os.getpid()}"
        if final.exists():
            final.rename(old)
        staging.rename(final)
        shutil.rmtree(old, ignore_errors=True)
        self._drop_resume(stage)
        # Downstream stages are now stale through their recorded upstream fingerprints.


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def _read_lock(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _lock_alive(holder: dict[str, Any]) -> bool:
    if holder.get("host") != socket.gethostname():
        return True  # cannot check another host's processes: assume alive
    pid = holder.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
