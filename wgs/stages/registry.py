"""The pipeline's stages in the order they run: one line per stage (its facts are its own, in
`stages/<name>/settings.py`). The workspace, the command line, the config file and the estimate
are derived from it."""

from __future__ import annotations

from typing import Any

from .baseline.settings import STAGE as BASELINE
from .coarse.settings import STAGE as COARSE
from .eval.settings import STAGE as EVAL
from .fine.settings import STAGE as FINE
from .finetune.settings import STAGE as FINETUNE
from .mask_data.settings import STAGE as MASK_DATA
from .prepare.settings import STAGE as PREPARE
from .repair.settings import STAGE as REPAIR
from .stage import Stage, StageEnv

REGISTRY: tuple[Stage, ...] = (PREPARE, COARSE, MASK_DATA, FINETUNE, REPAIR, FINE, BASELINE, EVAL)
STAGE: dict[str, Stage] = {s.name: s for s in REGISTRY}
METHOD: tuple[str, ...] = tuple(s.name for s in REGISTRY if s.method)  # what a reconstruction runs, in order
UNASKED: tuple[str, ...] = tuple(s.name for s in REGISTRY if not s.on_request)  # what `wgs all` runs unasked


def stages_through(name: str) -> tuple[str, ...]:
    """The method's stages up to and including `name`."""
    return METHOD[: METHOD.index(name) + 1]


def run_stage(name: str, ws: Any, cfg: Any, env: StageEnv, force: bool = False) -> bool:
    """Run stage `name` in `ws` (a `Workspace`) with settings `cfg`; False when it was up to date and skipped."""
    return STAGE[name].run(ws, cfg, env, force)
