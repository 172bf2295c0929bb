"""The mask-data stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import Calibration, SceneFacts, StageCost, cover_factor, loop_s
from ...fields import option
from ...gaussians.trainer import TrainConfig
from ..stage import FAST_TRAINING, Stage, StageEnv

FACTOR = 0.92  # time / modelled work on whole runs: lego at 200 px and ethiopianHead at 307 px, then times 1.15 to fit
# six kinds of capture with the hull's plateau (docs/speed.md, "The plateau expected from the hull")


@dataclass
class MaskDataConfig(TrainConfig):
    """Training of G_d (or the N leave-one-out models) and the corrupted/clean pairs it yields."""

    iterations: int = 1500
    strategy: str = option(
        "orm",
        "Pair generation: orm online random masking, offline-rm static masks, loo leave-one-out.",
        choices=("orm", "offline-rm", "loo"),
    )
    n_regions: int = option(10, "Mask regions per view.")
    coverage: float = option(0.5, "Hidden fraction of the object area.")
    drift: float = 0.08  # sinusoidal displacement amplitude, fraction of the object's size
    drift_period: float = 400.0  # iterations
    warmup: int = 500  # no pairs before this iteration
    pair_every: int = 100
    half_size_until: float = 0.3


def run(ws: Any, cfg: MaskDataConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_mask_data  # on first use: the stage loads the library

    return run_mask_data(ws, cfg, env, force)


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """G_d, or one model per training view leaving it out (loo)."""
    cfg: MaskDataConfig = cfgs["mask_data"]
    return StageCost(
        fixed_steps=15,
        loops=facts.n_train if cfg.strategy == "loo" else 1,
        loop_s=loop_s(cal, cfg, facts.pixels),
        factor=FACTOR * cover_factor(facts),
    )


STAGE = Stage(
    "mask_data",
    "2_mask_data",
    MaskDataConfig,
    ("prepare", "coarse"),
    run,
    "Corrupted/clean pairs for the repair models (trains G_d, or N models for loo).",
    cost,
    outputs={"index": "index.json"},  # the corrupted / clean pairs, paths relative to it
    presets={
        "fast": {
            **FAST_TRAINING,
            "iterations": 200,
            "refine_stop": 150,
            "warmup": 60,
            "pair_every": 28,
            "drift_period": 100.0,
        }
    },
    all_options=("strategy",),
)
