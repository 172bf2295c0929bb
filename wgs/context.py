"""The global options of a `wgs` run as a plain object (built by the CLI, read by orchestration)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .config import STAGES, resolve
from .errors import WgsError
from .progress import log
from .workspace import Workspace


@dataclass
class RunOptions:
    """What every command shares: the global options and the config file's tables. The pipeline,
    the ablation and the batch runner take this plain object, never click's context."""

    workspace: Path | None
    device: str
    seed: int
    debug: bool
    file_cfg: dict[str, Any] = field(default_factory=dict)
    resume: bool = False
    checkpoint_every: float = 60.0
    config_path: Path | None = None

    def child_args(self) -> list[str]:
        """The global options again, for a `wgs` child process (wgs batch)."""
        out = ["--seed", str(self.seed), "--checkpoint-every", str(self.checkpoint_every)]
        if self.device != "auto":
            out += ["--device", self.device]
        if self.config_path is not None:
            out += ["--config", str(self.config_path.resolve())]
        if self.resume:
            out.append("--resume")
        return out

    def ws(self) -> Workspace:
        if self.workspace is None:
            raise WgsError("no workspace: pass -w/--workspace DIR")
        return Workspace(self.workspace, resume=self.resume, checkpoint_every=self.checkpoint_every)

    def config(self, stage: str, preset: str | None, **cli: Any) -> Any:
        return resolve(stage, preset or self.file_cfg.get("global", {}).get("preset"), self.file_cfg, cli)

    def configs(self, preset: str | None, overrides: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
        """Every stage's config (config table -> settings), with per-table CLI `overrides`."""
        return {t: self.config(t, preset, **(overrides or {}).get(t, {})) for t in STAGES}

    def torch_device(self):
        from .device import resolve_device
        from .gaussians.render import pick_backend

        dev = resolve_device(self.device)
        backend = pick_backend(dev)
        slow = (
            " (the reference: slower than numba on a CPU; pip install 'wgs[cuda]' for gsplat)"
            if (dev.type != "cpu" and backend == "torch")
            else ""
        )
        log(f"device: {dev}, rasterizer: {backend}{slow}")
        if backend == "numba":
            from . import kernels

            if not kernels.cached():
                where = kernels.cache_dir()
                log(f"numba: compiling the CPU kernels, once (about half a minute on 2 cores; cached in {where})")
                log(f"numba: compiled in {kernels.compile_kernels():.0f} s")
        return dev

    def env(self, device=None, **kw: Any):
        """The stages' `StageEnv` for this run (`device`: one already resolved, else resolved here)."""
        from .stages.stage import StageEnv

        return StageEnv(**{"device": device if device is not None else self.torch_device(), "seed": self.seed, **kw})

    def run(self, name: str, cfg: Any, force: bool = False, ws: Workspace | None = None, **env: Any) -> bool:
        """Run one stage in this run's workspace (or `ws`) through the registry."""
        from .stages.registry import run_stage

        return run_stage(name, ws if ws is not None else self.ws(), cfg, self.env(**env), force)
