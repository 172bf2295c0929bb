"""The coarse stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import (
    EXPECTED_PLATEAU,
    Calibration,
    SceneFacts,
    StageCost,
    cover_factor,
    expected_iterations,
    loop_s,
    side_by_side_share,
)
from ...fields import option
from ...gaussians.stopping import StopParams, pilot_cap, stop_iteration
from ...gaussians.trainer import TrainConfig
from ...threads import side_by_side
from ..stage import FAST_TRAINING, MODEL_OUTPUTS, CurveConfig, Stage, StageEnv

MEMBERS_FROM_PILOTS = ("early", "always", "never")  # `members_from_pilots`'s choices
FACTOR = 1.15  # time / modelled work on whole runs: lego at 200 px and ethiopianHead at 307 px, then times 1.15 to fit
# six kinds of capture with the hull's plateau (docs/speed.md, "The plateau expected from the hull")
# the models' time over their modelled work once the pilots ran and the stop is known (the worker
# processes' start, the outputs, the side-by-side models slower than their modelled share): lego's
# 4 views at 200 px, 72.6 s against 54.9 s with the models started in their own order, times 0.853
# for the longest first (`run.longest_first`; docs/speed.md, "The estimate of the rest, once the pilots ended")
MODELS_FACTOR = 1.13


@dataclass
class CoarseConfig(CurveConfig, StopParams, TrainConfig):
    iterations: int = 1500
    # coarse models trained with seeds seed .. seed + ensemble - 1 (the first is G_c); the repair
    # averages their repaired renders: their sparse-view artifacts differ, the object does not
    # (docs/repair-prior.md)
    ensemble: int = option(
        6,
        "Coarse models from consecutive seeds; the repair averages their repaired renders (1: G_c alone).",
        bounds=(1, None),
    )
    half_size_until: float = 0.3
    # the share of the schedule at half size for the ensemble's other models (not G_c): the repair
    # averages their renders, and their later iterations at full size cost most (docs/speed.md)
    member_half_size_until: float = option(0.6, bounds=(0.0, 1.0))
    # which of the ensemble's other models carry on from the held-out rule's pilots, one each, from
    # where the pilot ended, given back the photo it held out. early: where the rule stops the models
    # before their last iteration (members that fit the photos less, where fitting them more loses);
    # always; never (docs/speed.md)
    members_from_pilots: str = option("early", choices=MEMBERS_FROM_PILOTS)


def model_config(cfg: CoarseConfig, index: int) -> CoarseConfig:
    """The settings of the ensemble's model `index` (0: G_c)."""
    return cfg if index == 0 else dataclasses.replace(cfg, half_size_until=cfg.member_half_size_until)


def run(ws: Any, cfg: CoarseConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_coarse  # on first use: the stage loads the library

    return run_coarse(ws, cfg, env, force)


def pilot_iterations(cfg: CoarseConfig, plateau: int = EXPECTED_PLATEAU) -> int:
    """A pilot's expected length: `stop_patience` past the expected `plateau`, or, where that plateau
    leaves the run all its iterations, the plateau (by then a pilot has shown it, `plateau_past`);
    at most `pilot_cap`; 0 where the held-out rule is off."""
    if cfg.stop != "held-out" or cfg.max_seconds:
        return 0
    late = plateau > cfg.iterations / cfg.stop_margin
    return min(
        pilot_cap(cfg.iterations, cfg.stop_margin, cfg.stop_patience),
        plateau + (0 if late else cfg.stop_patience),
    )


def pilots_s(cal: Calibration, cfg: CoarseConfig, facts: SceneFacts, workers: int) -> float:
    """The held-out rule's pilots: one per photo (at most `stop_pilots`) at half size, each
    `pilot_iterations` long."""
    return (
        math.ceil(min(facts.n_train, cfg.stop_pilots) / workers)
        * pilot_iterations(cfg, facts.expected_plateau)
        * cal.view_s(facts.pixels / 4)
        * side_by_side_share(workers)
    )


def model_start(cfg: CoarseConfig, facts: SceneFacts, index: int) -> int:
    """The iteration the ensemble's model `index` starts from: where its pilot ended, for the
    members that carry on from one (`members_from_pilots`; "early": where the models are expected
    to stop before their last iteration; once the pilots ran, `facts.pilot_ends`, a member whose
    pilot ended at or past the models' stop trains from the start), else 0."""
    when = cfg.members_from_pilots
    end = expected_iterations(cfg, facts.expected_plateau)
    chosen = when == "always" or (when == "early" and end < cfg.iterations)
    if not chosen or not 1 <= index <= min(facts.n_train, cfg.stop_pilots):
        return 0
    if not facts.pilot_ends:
        return pilot_iterations(cfg, facts.expected_plateau)
    ended = facts.pilot_ends[index - 1] if index - 1 < len(facts.pilot_ends) else end
    return ended if ended < end else 0


def with_found_stop(cfg: CoarseConfig, facts: SceneFacts) -> CoarseConfig:
    """`cfg` stopped where the pilots' plateau puts the models, once they ran (`facts.plateau`)."""
    if facts.plateau is None or cfg.stop != "held-out" or cfg.max_seconds or cfg.end_iteration:
        return cfg
    end = stop_iteration(facts.plateau, cfg.stop_margin, cfg.stop_min_iterations, cfg.iterations)
    return dataclasses.replace(cfg, end_iteration=end)


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """The ensemble's models, side by side where that pays, after the held-out rule's pilots; the
    members that carry on from a pilot train from where it ended. Once the pilots ran
    (`facts.plateau`): the models alone, to the stop the pilots found."""
    cfg = with_found_stop(cfgs["coarse"], facts)
    on_cpu = cal.device.split(":")[0] == "cpu"
    workers = side_by_side(cfg.ensemble, cfg.iterations, facts.pixels, on_cpu)
    pilots = side_by_side(min(facts.n_train, cfg.stop_pilots), cfg.iterations, facts.pixels // 4, on_cpu)
    factor = FACTOR * cover_factor(facts) * (MODELS_FACTOR if facts.plateau is not None else 1.0)
    models = [
        loop_s(
            cal, model_config(cfg, i), facts.pixels, start=model_start(cfg, facts, i), plateau=facts.expected_plateau
        )
        for i in range(cfg.ensemble)
    ]
    return StageCost(
        fixed_steps=25,
        loops=math.ceil(cfg.ensemble / workers),
        loop_s=statistics.fmean(models) * side_by_side_share(workers),
        factor=factor,
        other_s=0.0 if facts.plateau is not None else factor * pilots_s(cal, cfg, facts, pilots),
    )


STAGE = Stage(
    "coarse",
    "1_coarse",
    CoarseConfig,
    ("prepare",),
    run,
    "Train the coarse 3DGS G_c on the training views.",
    cost,
    outputs={
        **MODEL_OUTPUTS,
        "members": "members",  # the ensemble's other models, members/ckpt_<i>.pt (i >= 1)
        "subbands": "subbands",  # Haar subbands of the training views, subbands/{ref,render}/<stem>.exr
    },
    presets={
        # 400 iterations leave the held-out rule's pilots (about a model's cost) nothing to save
        "fast": {
            **FAST_TRAINING,
            "iterations": 400,
            "refine_stop": 300,
            "ensemble": 1,
            "stop": "iterations",
            "member_half_size_until": 0.0,  # full size, as FAST_TRAINING's G_c
        },
        "paper": {
            "iterations": 10000,
            "refine_stop": 7000,
            "sh_degree": 3,
            "max_gaussians": 1000000,
            "init_points": 100000,
            "hull_resolution": 128,
            "reset_every": 3000,
            "stop": "iterations",  # the paper's schedule, run to its end
        },
    },
    all_options=("ensemble",),
)
