"""`wgs batch`: many scenes, each `wgs all` in its own process and workspace `ROOT/<name>/`.

Executors: a local pool (`--jobs N` on the CPU, one job per visible GPU), submitit (Slurm job
arrays; its local/debug executors run without a cluster), and a static shard `--rank i
--world-size n` of the scene list for any other scheduler. The summary aggregates every scene's
`6_eval/results.json` into `ROOT/_batch/summary.{json,csv}`.
"""

from __future__ import annotations

import csv
import glob
import io
import json
import os
import queue
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import InputError
from .io import atomic_write_bytes, atomic_write_json
from .progress import fmt, log
from .threads import COUNT_VARS, ENV, available_cores
from .workspace import Workspace

BATCH_DIR = "_batch"
DONE = "batch_done.json"
ERROR = "error.txt"
METRICS = ("psnr", "ssim", "lpips")


@dataclass(frozen=True)
class SceneTask:
    """One line of the scene list: a scene folder and extra `wgs all` options."""

    name: str
    scene: str  # absolute path
    options: tuple[str, ...] = ()


# ----------------------------------------------------------------------------- the scene list
# check_options(scene, options) -> why `wgs all` would refuse them (None: it takes them)
OptionsCheck = Callable[[Path, list[str]], str | None]


def read_scene_list(spec: str, check_options: OptionsCheck) -> list[SceneTask]:
    """SCENES: a text file (one scene folder per line, then optional `wgs all` options; `#` starts a
    comment; paths relative to the file) or a glob of scene folders."""
    path = Path(spec)
    tasks: list[SceneTask] = []
    if path.is_file():
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError:
            raise InputError("the scene list is not UTF-8 text", path) from None
        for n, line in enumerate(lines, 1):
            try:
                tokens = shlex.split(line, comments=True)
            except ValueError as exc:
                raise InputError(f"line {n}: {exc}", path) from None
            if not tokens:
                continue
            scene = (path.parent / tokens[0]).resolve()
            tasks.append(make_task(scene, tokens[1:], check_options, f"line {n}: ", path))
    else:
        matches = sorted(p for p in glob.glob(spec) if Path(p).is_dir())
        if not matches:
            raise InputError("no scene list file of that name and no scene folder matches it as a glob", spec)
        tasks = [make_task(Path(m).resolve(), [], check_options, "", spec) for m in matches]
    if not tasks:
        raise InputError("the scene list names no scene", spec)
    seen: dict[str, str] = {}
    for t in tasks:
        if t.name in seen:
            raise InputError(
                f"two scenes are named {t.name!r} ({seen[t.name]} and {t.scene}): their workspaces "
                "would collide; rename one folder or list it under another parent",
                spec,
            )
        seen[t.name] = t.scene
    return tasks


def make_task(scene: Path, options: list[str], check: OptionsCheck, where: str, source: str | Path) -> SceneTask:
    if not scene.is_dir():
        raise InputError(f"{where}scene folder not found: {scene}", source)
    if any(o in ("-w", "--workspace") or o.startswith("--workspace=") for o in options):
        raise InputError(f"{where}-w is set by wgs batch (ROOT/<scene name>)", source)
    refused = check(scene, options)  # `wgs all`'s own parsing: a typo fails here, not an hour later
    if refused is not None:
        raise InputError(f"{where}{refused}", source)
    return SceneTask(scene.name, str(scene), tuple(options))


def shard(tasks: list[SceneTask], rank: int, world_size: int) -> list[SceneTask]:
    """Scenes rank, rank + n, rank + 2n, ... of the list: the ranks 0..n-1 cover each scene once."""
    return tasks[rank::world_size]


def shard_from_env(rank: int | None, world_size: int | None) -> tuple[int, int]:
    """--rank/--world-size, else Slurm array variables (SLURM_ARRAY_TASK_ID - SLURM_ARRAY_TASK_MIN of
    SLURM_ARRAY_TASK_COUNT), else the whole list."""
    env = os.environ
    if rank is None and "SLURM_ARRAY_TASK_ID" in env and "SLURM_ARRAY_TASK_COUNT" in env:
        rank = int(env["SLURM_ARRAY_TASK_ID"]) - int(env.get("SLURM_ARRAY_TASK_MIN", "0"))
        world_size = int(env["SLURM_ARRAY_TASK_COUNT"])
    rank = 0 if rank is None else rank
    world_size = 1 if world_size is None else world_size
    if world_size < 1 or not 0 <= rank < world_size:
        raise InputError(f"rank {rank} is not in 0..{world_size - 1} (world size {world_size})")
    return rank, world_size


# ----------------------------------------------------------------------------- one scene
def run_scene(
    task: SceneTask,
    root: str,
    global_args: list[str],
    env: dict[str, str] | None = None,
    rerun: bool = False,
    resume: bool = False,
    started: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """`wgs all` on one scene in a child process (a crash or a GPU fault stays there). Writes
    ROOT/<name>/error.txt on failure, ROOT/<name>/batch_done.json on success; a scene finished with
    the same arguments is skipped unless `rerun`. `resume`: continue a stage that a stopped run
    saved (`wgs --resume`); `started(pid)` is told the child's process id."""
    ws = Path(root) / task.name
    again = ["--resume"] if resume and "--resume" not in global_args else []
    args = [*global_args, *again, "-w", str(ws), "all", task.scene, *task.options]
    key = {"args": [*global_args, "all", task.scene, *task.options]}
    done = ws / DONE
    if not rerun and done.is_file() and _read(done) == key and Workspace(ws).output("eval", "results").is_file():
        return {"name": task.name, "status": "skipped", "seconds": 0.0, "error": None}
    logs = Path(root) / BATCH_DIR / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    ws.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    # resuming: the log goes on after the stopped run's
    with open(logs / f"{task.name}.log", "a" if resume else "w", encoding="utf-8") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "wgs", *args], stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}
        )
        if started is not None:
            started(proc.pid)
        proc.wait()
    seconds = time.perf_counter() - t0
    if proc.returncode == 0:
        (ws / ERROR).unlink(missing_ok=True)
        atomic_write_json(done, key)
        return {"name": task.name, "status": "done", "seconds": round(seconds, 2), "error": None}
    message = failure_message(logs / f"{task.name}.log", proc.returncode)
    done.unlink(missing_ok=True)
    atomic_write_bytes(
        ws / ERROR,
        (
            f"{message}\nexit status {proc.returncode}; command: wgs "
            f"{shlex.join(args)}\nfull log: {logs / (task.name + '.log')}\n"
        ).encode(),
    )
    return {"name": task.name, "status": "failed", "seconds": round(seconds, 2), "error": message}


def failure_message(log_file: Path, returncode: int) -> str:
    """The child's `error:` line, else the last line of its output, else its exit status."""
    lines = [ln.strip() for ln in log_file.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith(("error:", "interrupted:"))]
    if errors:
        return errors[-1]
    if returncode < 0:
        return f"killed by signal {-returncode}"
    return lines[-1] if lines else f"exit status {returncode}"


def _read(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


# ----------------------------------------------------------------------------- executors
def visible_gpus() -> list[str]:
    """GPU ids a child may be pinned to: CUDA_VISIBLE_DEVICES when set, else what torch sees."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [g for g in env.split(",") if g.strip() and g.strip() != "-1"]
    try:
        import torch

        return [str(i) for i in range(torch.cuda.device_count())]
    except Exception:  # noqa: BLE001 - no torch CUDA runtime: no GPUs
        return []


def run_local(
    tasks: list[SceneTask], root: Path, global_args: list[str], jobs: int | None, use_gpus: bool, rerun: bool = False
) -> list[dict[str, Any]]:
    """A pool of child processes: one per visible GPU (CUDA_VISIBLE_DEVICES set per child), else `jobs`
    on the CPU with the cores shared out (WGS_THREADS per child, see threads.py)."""
    gpus = visible_gpus() if use_gpus else []
    n = max(1, jobs if jobs is not None else (len(gpus) or 1))
    if gpus:  # each child sees one GPU as cuda:0
        global_args = ["cuda" if a.startswith("cuda:") else a for a in global_args]
    slots: queue.Queue[dict[str, str]] = queue.Queue()
    if gpus:
        n = min(n, len(gpus))
        for g in gpus[:n]:
            slots.put({"CUDA_VISIBLE_DEVICES": g})
    else:
        threads = str(max(1, available_cores() // n))  # share the cores out instead of oversubscribing
        for _ in range(n):
            slots.put({ENV: threads, **{k: threads for k in COUNT_VARS}})
    log(f"batch: {len(tasks)} scene(s), {n} at a time" + (f" on GPUs {', '.join(gpus[:n])}" if gpus else " on the CPU"))

    def one(i_task: tuple[int, SceneTask]) -> dict[str, Any]:
        i, task = i_task
        env = slots.get()
        try:
            res = run_scene(task, str(root), global_args, env, rerun)
        finally:
            slots.put(env)
        log(
            f"batch: [{i + 1}/{len(tasks)}] {task.name}: {res['status']}"
            + (f" in {res['seconds']:.0f} s" if res["status"] != "skipped" else "")
            + (f" ({res['error']})" if res["error"] else "")
        )
        return res

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(one, enumerate(tasks)))


@dataclass
class SlurmOptions:
    """What `run_submitit` asks of Slurm (the meanings and defaults: `cli.batch.BatchSettings`)."""

    cluster: str | None  # None: Slurm when available (submitit's auto); "local"/"debug": no cluster
    partition: str | None
    time_min: int
    gpus: int
    cpus: int
    mem_gb: int | None
    array_parallelism: int
    signal_s: int  # Slurm signals a job this many seconds before its time limit
    requeues: int  # times a job stopped at its time limit is requeued


def exited(pid: int) -> bool:
    """Whether child `pid` has exited (it stays waitable: its Popen reaps it later)."""
    try:
        return os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
    except ChildProcessError:  # already reaped
        return True


class SceneJob:
    """One scene as a Slurm job (submitit): `wgs --resume all`, so that a requeued job continues from
    what its stopped run saved.

    At a job's time limit (`--signal`, `signal_s` before it) and at preemption Slurm signals every
    process of the job step: the `wgs` child saves and stops (`resume.STOP_SIGNALS`), and submitit's
    handler in this process calls `checkpoint`, which waits for the child to exit and hands back the
    same call; submitit then requeues the job (`scontrol requeue`). A scene that finished is
    skipped by the requeued job (`run_scene`)."""

    SAVE_WAIT_S = 600.0  # the longest a stopping child is waited for (one iteration and a save)
    # a child stopped by Slurm's SIGTERM (preemption, scancel): the job waits this long for Slurm to
    # end it, so that a job being requeued does not report the stop as the scene's result first
    # (on Slurm only: submitit's local executor has no one to end it)
    STOPPED_WAIT_S = 300.0

    def __init__(self) -> None:
        self.child: int | None = None

    def __call__(self, task: SceneTask, root: str, global_args: list[str], rerun: bool) -> dict[str, Any]:
        res = run_scene(task, root, global_args, None, rerun, resume=True, started=self._started)
        stopped = res["status"] == "failed" and (res["error"] or "").startswith("interrupted:")
        if stopped and os.environ.get("SUBMITIT_EXECUTOR") == "slurm":
            time.sleep(self.STOPPED_WAIT_S)
        return res

    def _started(self, pid: int) -> None:
        self.child = pid

    def checkpoint(self, *args: Any, **kwargs: Any) -> Any:
        from submitit.helpers import DelayedSubmission

        end = time.monotonic() + self.SAVE_WAIT_S
        while self.child is not None and not exited(self.child) and time.monotonic() < end:
            time.sleep(0.2)
        return DelayedSubmission(SceneJob(), *args, **kwargs)

    def __getstate__(self) -> dict[str, Any]:  # the child's pid means nothing in the requeued job
        return {"child": None}


def run_submitit(
    tasks: list[SceneTask], root: Path, global_args: list[str], opts: SlurmOptions, rerun: bool = False
) -> list[dict[str, Any]]:
    """One job-array element per scene; logs in ROOT/_batch/logs/<job id>/. Waits for the results."""
    try:
        import submitit
    except ImportError:
        raise InputError("--executor slurm needs submitit: pip install 'wgs[slurm]'") from None
    folder = root / BATCH_DIR / "logs" / "%j"
    executor = submitit.AutoExecutor(folder=folder, cluster=opts.cluster, slurm_max_num_timeout=opts.requeues)
    executor.update_parameters(
        timeout_min=opts.time_min,
        gpus_per_node=opts.gpus or None,
        cpus_per_task=opts.cpus,
        mem_gb=opts.mem_gb,
        name="wgs-batch",
        slurm_partition=opts.partition,
        slurm_array_parallelism=opts.array_parallelism,
        slurm_signal_delay_s=opts.signal_s,
    )
    n = len(tasks)
    jobs = executor.map_array(SceneJob(), tasks, [str(root)] * n, [global_args] * n, [rerun] * n)
    log(f"batch: submitted {n} job(s) to {executor.cluster} (first id {jobs[0].job_id if jobs else '-'})")
    out = []
    for task, job in zip(tasks, jobs, strict=True):
        try:
            res = job.result()
        except Exception as exc:  # noqa: BLE001 - the job itself died (time limit, node failure, ...)
            msg = str(exc).strip().splitlines()[-1][:300] if str(exc).strip() else type(exc).__name__
            res = {"name": task.name, "status": "failed", "seconds": None, "error": f"job {job.job_id}: {msg}"}
            atomic_write_bytes(root / task.name / ERROR, (res["error"] + "\n").encode())
        log(f"batch: {task.name}: {res['status']}" + (f" ({res['error']})" if res["error"] else ""))
        out.append(res)
    return out


# ----------------------------------------------------------------------------- summary
def summarize(root: Path, tasks: list[SceneTask], ran: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """Every scene of the list (run now or before): status, metrics, stage times; mean and std."""
    rows = []
    for t in tasks:
        ws = root / t.name
        res = _read(Workspace(ws).output("eval", "results"))
        err = (ws / ERROR).read_text(encoding="utf-8").splitlines()[0] if (ws / ERROR).is_file() else None
        status = "failed" if err else ("done" if isinstance(res, dict) else "not run")
        row: dict[str, Any] = {"scene": t.name, "path": t.scene, "status": status, "error": err}
        if status == "done":
            times = res.get("stage_times_s") or {}
            row.update({m: res.get(m) for m in METRICS})
            row.update({f"coarse_{m}": (res.get("coarse") or {}).get(m) for m in METRICS})
            row["total_time_s"] = round(sum(v for v in times.values() if isinstance(v, int | float)), 2)
            row["stage_times_s"] = times
        if ran and t.name in ran:
            row["this_run"] = ran[t.name]["status"]
        rows.append(row)
    done = [r for r in rows if r["status"] == "done"]
    keys = [*METRICS, *(f"coarse_{m}" for m in METRICS), "total_time_s"]
    stages = sorted({s for r in done for s in r["stage_times_s"]})
    mean, std = {}, {}
    for k in keys + [f"time_{s}" for s in stages]:
        found = [(r["stage_times_s"].get(k[5:]) if k.startswith("time_") else r.get(k)) for r in done]
        vals = [float(v) for v in found if isinstance(v, int | float)]
        mean[k] = statistics.fmean(vals) if vals else None
        std[k] = statistics.pstdev(vals) if len(vals) > 1 else (0.0 if vals else None)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "failed", "not run")}
    return {"root": str(root), "counts": counts, "scenes": rows, "mean": mean, "std": std, "stages": stages}


def write_summary(root: Path, summary: dict[str, Any]) -> None:
    out = root / BATCH_DIR
    atomic_write_json(out / "summary.json", summary)
    cols = [
        "scene",
        "status",
        *METRICS,
        *(f"coarse_{m}" for m in METRICS),
        "total_time_s",
        *(f"time_{s}" for s in summary["stages"]),
        "error",
    ]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    for r in summary["scenes"]:
        w.writerow([r.get(c) if not c.startswith("time_") else (r.get("stage_times_s") or {}).get(c[5:]) for c in cols])
    for label in ("mean", "std"):
        w.writerow([label, "", *(summary[label].get(c) for c in cols[2:-1]), ""])
    atomic_write_bytes(out / "summary.csv", buf.getvalue().encode())


def print_summary(summary: dict[str, Any]) -> None:
    from rich.table import Table

    from .progress import results

    rows, m, sd = summary["scenes"], summary["mean"], summary["std"]
    # (header, row key, decimals); LPIPS and error columns only when some scene has them
    cols = [
        ("PSNR", "psnr", 2),
        ("SSIM", "ssim", 3),
        ("LPIPS", "lpips", 3),
        ("PSNR G_c", "coarse_psnr", 2),
        ("time (s)", "total_time_s", 1),
    ]
    cols = [c for c in cols if c[1] != "lpips" or any(r.get("lpips") is not None for r in rows)]
    with_errors = any(r["error"] for r in rows)
    table = Table(title=f"wgs batch: {summary['root']}")
    table.add_column("scene", no_wrap=True, min_width=min(40, max(len(r["scene"]) for r in rows)))
    for c in ("status", *(c[0] for c in cols), *(["error"] if with_errors else [])):
        table.add_column(c, overflow="fold")
    for r in rows:
        status = r["status"] + (f" ({r['this_run']})" if r.get("this_run") == "skipped" else "")
        table.add_row(
            r["scene"],
            status,
            *(fmt(r.get(k), nd, missing="") for _, k, nd in cols),
            *([(r["error"] or "")[:120]] if with_errors else []),
        )
    table.add_row(
        "mean ± std",
        f"{summary['counts']['done']} done",
        *(f"{fmt(m[k], nd, '')} ± {fmt(sd[k], nd, '')}" if m.get(k) is not None else "" for _, k, nd in cols),
        *([""] if with_errors else []),
    )
    results.print(table)
