"""Pipeline stages: one module per stage, each with a run function of one signature,
`run(ws, cfg, env, force) -> bool` (False: up to date, skipped), found through the registry
(`config.REGISTRY`'s `runner`) by `run_stage`."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..config import REGISTRY

if TYPE_CHECKING:
    import torch

    from ..workspace import Workspace


class WorkingSize(Protocol):
    """Prepare's working size where neither downscale nor max_size is set: (photo width, height,
    training views, test views) -> (downscale, the line that says why). `key` names the rule; a
    change of it makes the prepared scene stale."""

    key: str

    def __call__(self, width: int, height: int, n_train: int, n_test: int) -> tuple[int, str]: ...


@dataclass(frozen=True)
class StageEnv:
    """What a stage's run takes besides its workspace and settings."""

    device: torch.device
    seed: int = 0
    scene_dir: Path | None = None  # prepare: the scene folder to import
    final: str = "fine"  # eval: the model it scores (fine, or coarse where the repair stages were left out)
    working_size: WorkingSize | None = None  # prepare: the size chosen for the machine; None: the photos' own


def stage_runner(name: str):
    """The run function of stage `name` (imported on first use: stages load torch and numba)."""
    entry = next(s for s in REGISTRY if s.name == name)
    module, function = entry.runner.split(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), function)


def run_stage(name: str, ws: Workspace, cfg: Any, env: StageEnv, force: bool = False) -> bool:
    """Run stage `name` in `ws` with settings `cfg`; False when it was up to date and skipped."""
    return stage_runner(name)(ws, cfg, env, force)
