"""The eval stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import Calibration, SceneFacts, StageCost
from ...fields import option
from ...gaussians.trainer import TrainConfig
from ..repair.settings import repaired_render_s
from ..stage import LpipsWeightsConfig, Stage, StageEnv

FACTOR = 0.9  # time / modelled work on whole runs (lego at 200 px, ethiopianHead at 307 px; docs/speed.md)
# one step of the test-camera localisation (render, backward, the Gaussians moved) in rendered
# views: 2.4 measured at 200x200 with 20k Gaussians (a random blob, tests/test_localise.py's)
LOCALISE_STEP_VIEWS = 2.5


@dataclass
class EvalConfig(LpipsWeightsConfig):
    lpips_net: str = option("alex", "LPIPS backbone.", choices=("alex", "vgg"))
    max_views: int | None = option(None, "Evaluate on the first N test views only.")
    repair_gain: bool = True  # also repair G_c's renders at the test poses and score them (the repair's own gain)
    # at this many test poses spread evenly over them (0: all): each repairs every member's render
    repair_gain_views: int = option(25, "Score the repair at N test poses spread over them (0: all).", bounds=(0, None))
    # the visual hull's grid (voxels along its box's side) whose silhouettes are scored at the test
    # views and, leaving each training view out in turn, at the training views
    hull_resolution: int = TrainConfig.hull_resolution
    localise_steps: int = option(
        60,
        "Photos posed by wgs: move each test camera this many steps to where the final model fits its photo best, "
        "and score there, as pose-free methods do (0: score at the posed cameras).",
        bounds=(0, None),
    )
    turntable_frames: int = 48  # a GIF of the final model on an orbit fitted to the training cameras; 0: none


def run(ws: Any, cfg: EvalConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_eval  # on first use: the stage loads the library

    return run_eval(ws, cfg, env, force)


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """The test views rendered (and localised where wgs posed the photos), the repair's gain at some
    of them with every member, and the turntable."""
    ev: EvalConfig = cfgs["eval"]
    view_s = cal.view_s(facts.pixels)
    n_eval = min(facts.n_test, ev.max_views or facts.n_test)
    gain = min(ev.repair_gain_views or n_eval, n_eval) if ev.repair_gain else 0
    per_render = repaired_render_s(cal, cfgs["finetune"], cfgs["repair"], facts)
    localise = n_eval * ev.localise_steps * LOCALISE_STEP_VIEWS * view_s if facts.posed_by_wgs else 0
    work = n_eval * view_s + gain * cfgs["coarse"].ensemble * per_render + ev.turntable_frames * view_s / 2 + localise
    return StageCost(fixed_steps=10, other_s=FACTOR * work)


STAGE = Stage(
    "eval",
    "6_eval",
    EvalConfig,
    ("prepare", "coarse", "repair", "fine", "baseline"),
    run,
    "PSNR, SSIM, LPIPS and silhouettes of G_f and G_c on the test views, and the error-against-time report.",
    cost,
    outputs={"results": "results.json", "report": "report.md", "report_html": "report.html"},
    all_options=("lpips_weights",),
    method=False,
)
