"""The baseline stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import Calibration, SceneFacts, StageCost
from ..stage import MODEL_OUTPUTS, Stage, StageEnv


@dataclass
class BaselineConfig:
    """Plain 3DGS (the coarse stage's trainer and settings, one model, no repair) trained for the
    time the pipeline's training stages took: what that time buys without WaveletGaussian."""

    # iteration and densification caps, as a multiple of G_c's own rate over the budget: the time
    # budget, not the caps, ends the training
    headroom: float = 4.0


def run(ws: Any, cfg: BaselineConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_baseline  # on first use: the stage loads the library

    return run_baseline(ws, cfg, env, force)


TRAINS_FOR = ("coarse", "mask_data", "finetune", "repair", "fine")  # the method's stages after prepare


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """As long as the method's stages after prepare."""
    return StageCost(fixed_steps=10, other_s=sum(before[t] for t in TRAINS_FOR))


STAGE = Stage(
    "baseline",
    "baseline",
    BaselineConfig,
    ("prepare", "coarse", "fine"),
    run,
    "Plain 3DGS trained for the pipeline's training time (what that time buys without the repair);\n"
    "eval then draws its curve beside the method's.",
    cost,
    outputs={"model": MODEL_OUTPUTS["model"], "curve": MODEL_OUTPUTS["curve"]},
    trains_for=TRAINS_FOR,
    method=False,
    on_request=True,
)
