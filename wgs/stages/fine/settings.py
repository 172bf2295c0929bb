"""The fine stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import Calibration, SceneFacts, StageCost, cover_factor, expected_follow_end, loop_s
from ...fields import option
from ...gaussians.stopping import StopRule
from ...gaussians.trainer import TrainConfig
from ..stage import FAST_TRAINING, MODEL_OUTPUTS, CurveConfig, LpipsWeightsConfig, Stage, StageEnv

FACTOR = 1.07  # time / modelled work on whole runs: lego at 200 px and ethiopianHead at 307 px, then times 1.15 to fit
# six kinds of capture with the hull's plateau (docs/speed.md, "The plateau expected from the hull")


@dataclass
class FineConfig(LpipsWeightsConfig, CurveConfig, StopRule, TrainConfig):
    """Refinement of G_c on the real and the pseudo references; under the held-out rule (`stop`)
    G_f stops at the coarse stage's margin times its pilots' plateau."""

    iterations: int = 1500
    refine_start: int = 100
    refine_stop: int = 1000
    half_size_until: float = 0.3  # real and pseudo views halved, as in the coarse stage
    # where G_f starts: "hull" trains afresh from the visual-hull init on the real and pseudo views
    # together (G_c's 4-view artifacts are not dragged along), "coarse" refines G_c, "auto" is hull
    # when the scene has masks (else there is no hull to start from)
    start: str = option(
        "auto",
        "Train G_f from the visual hull or from G_c (auto: the hull when the scene has masks).",
        choices=("auto", "coarse", "hull"),
    )
    pseudo_weight_start: float = 1.0  # a pseudo view's weight against a real view's at the start
    pseudo_weight_end: float = 1.0  # reached at pseudo_until of the iterations; 0 after (real views only)
    pseudo_until: float = 1.0  # fraction of the iterations with pseudo views (GaussianObject: 0.7)
    pseudo_every: int = 2  # one pseudo-view step every k iterations
    lpips_weight: float = 0.1  # LPIPS (VGG) on the pseudo views, used when its weights are on this machine
    rounds: int = option(1, "Rounds of repair + refinement: each later one repairs the refined model's renders again.")


def run(ws: Any, cfg: FineConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_fine  # on first use: the stage loads the library

    return run_fine(ws, cfg, env, force)


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """One loop per round, a pseudo view's step every `pseudo_every` iterations besides the photos'."""
    cfg: FineConfig = cfgs["fine"]
    cfg = dataclasses.replace(cfg, end_iteration=expected_follow_end(cfg, cfgs["coarse"], facts.plateau_or_expected))
    return StageCost(
        fixed_steps=10,
        loops=max(1, cfg.rounds),
        loop_s=loop_s(cal, cfg, facts.pixels, renders=1 + 1 / max(cfg.pseudo_every, 1)),
        factor=FACTOR * cover_factor(facts),
    )


STAGE = Stage(
    "fine",
    "5_fine",
    FineConfig,
    ("prepare", "coarse", "finetune", "repair"),  # fine rounds run the repair again: finetune's models too
    run,
    "Train G_f on the real and the pseudo references.",
    cost,
    outputs=dict(MODEL_OUTPUTS),
    presets={"fast": {**FAST_TRAINING, "iterations": 300, "refine_start": 50, "refine_stop": 200}},
    all_options=("lpips_weights",),
)
