"""The repair stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import Calibration, SceneFacts, StageCost
from ...fields import option
from ...gaussians.trainer import TrainConfig
from ...shape.carve import CarveParams
from ...shape.own_shape import OwnShapeParams
from ..finetune.settings import FinetuneConfig, d_pixels
from ..stage import Stage, StageEnv

FACTOR = 0.9  # time / modelled work on whole runs (lego at 200 px, ethiopianHead at 307 px; docs/speed.md)


@dataclass
class RepairConfig(OwnShapeParams, CarveParams):
    """Pseudo references at novel poses, the visual hull shrunk by what the photos' masks allow
    (`shape.own_shape.OwnShapeParams`), and its carving by the volume model V and the silhouette
    model S (the thresholds come from `shape.carve.CarveParams`)."""

    poses: str = option(
        "sphere",
        "Pseudo viewpoints: a band over the view sphere or arcs between training views.",
        choices=("sphere", "arc"),
    )
    num_views: int = option(24, "Pseudo views in all (sphere poses).")
    # sphere: the band's elevations, from band_below degrees under the lowest training camera to
    # band_above over the highest
    band_below: float = 15.0
    band_above: float = 40.0
    views_per_train: int = option(2, "Novel viewpoints per training view (arc poses).")
    arc_min: float = 0.3  # fraction of the arc between neighbouring training cameras
    arc_max: float = 0.7
    strength: float = option(
        0.5, "SDEdit strength (noise level) of a from-scratch D's repair (a prior's D runs one step)."
    )
    steps: int = option(10, "DDIM steps of a from-scratch D's repair.")
    # D repairs each render under this many flips / transposes of it (1..8), averaged; ensemble
    # members take different ones, so D's errors differ between them
    symmetries: int = option(1, bounds=(1, 8))
    # The visual hull (every mask agreeing) is carved where the volume model V is sure of background,
    # then where the silhouette model S is sure at the pseudo views; G_f starts from the carved hull
    # and learns opacity at the pseudo views inside its outline. Needs masks and V's or S's weights
    carve: bool = option(True, "The volume model V and the silhouette model S carve the visual hull.")
    silhouette_model: str = "builtin"  # builtin: wgs/weights/S; or a folder holding S
    volume_model: str = "builtin"  # builtin: wgs/weights/V; or a folder holding V
    hull_resolution: int = TrainConfig.hull_resolution  # voxels along the carved hull's box
    carve_views: int = 32  # S also predicts at this many views over the whole sphere, for carving only


def run(ws: Any, cfg: RepairConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_repair  # on first use: the stage loads the library

    return run_repair(ws, cfg, env, force)


def pseudo_views(cfg: RepairConfig, n_train: int) -> int:
    return cfg.num_views if cfg.poses == "sphere" else cfg.views_per_train * n_train


def repaired_render_s(cal: Calibration, finetune: FinetuneConfig, cfg: RepairConfig, facts: SceneFacts) -> float:
    """One member's render at a pseudo view, repaired (this stage's unit, and eval's repair gain's)."""
    forwards = math.ceil(cfg.steps * cfg.strength) * cfg.symmetries
    return forwards * d_pixels(finetune, facts) * cal.d_forward_s_per_pixel + cal.view_s(facts.pixels) / 2


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """Every member's render at every pseudo view, repaired, once per round of the fine stage."""
    rp: RepairConfig = cfgs["repair"]
    per_render = repaired_render_s(cal, cfgs["finetune"], rp, facts)
    rounds = max(1, cfgs["fine"].rounds)
    return StageCost(
        fixed_steps=35,
        other_s=FACTOR * cfgs["coarse"].ensemble * pseudo_views(rp, facts.n_train) * per_render * rounds,
    )


STAGE = Stage(
    "repair",
    "4_repair",
    RepairConfig,
    ("prepare", "coarse", "finetune"),
    run,
    "Render G_c at novel views and repair them with D and U -> pseudo references.",
    cost,
    outputs={
        "views": "views.json",  # the pseudo views' cameras and weights (and S's silhouette files)
        "silhouettes": "silhouettes",  # per pseudo view, where the object may be (black: S is sure of background)
        "carved_hull": "carved_hull.npz",  # the visual hull carved by V and S (shape.hull.save_grid)
        "pseudo": "pseudo",  # the pseudo references, <stem>.exr (RGB, float) and <name> (PNG)
        "contact_sheet": "contact_sheet.png",
    },
    presets={"fast": {"steps": 5, "num_views": 16, "band_above": 25.0}},
    all_options=("carve", "shape_revolution", "shape_smooth"),
)
