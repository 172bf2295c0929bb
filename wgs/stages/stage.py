"""What a stage is (`Stage`): the facts the registry (`stages.registry`), the command line, the
workspace and the estimate read, each stated once in the stage's own settings module
(`stages/<name>/settings.py`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ..cost import Calibration, SceneFacts, StageCost
from ..fields import facts, option

if TYPE_CHECKING:
    import torch


class WorkingSize(Protocol):
    """Prepare's working size where neither downscale nor max_size is set: (photo width, height,
    training views, test views, whether it will have masks, the share of a training photo inside
    its given mask or None where the masks are yet to be made) -> (downscale, the line that says
    why). `key` names the rule; a change of it makes the prepared scene stale."""

    key: str

    def __call__(
        self, width: int, height: int, n_train: int, n_test: int, has_masks: bool, mask_share: float | None = None
    ) -> tuple[int, str]: ...


@dataclass(frozen=True)
class StageEnv:
    """What a stage's run takes besides its workspace and settings."""

    device: torch.device
    seed: int = 0
    scene_dir: Path | None = None  # prepare: the scene folder to import
    final: str = "fine"  # eval: the model it scores (fine, or coarse where the repair stages were left out)
    working_size: WorkingSize | None = None  # prepare: the size chosen for the machine; None: the photos' own
    # coarse: given the held-out rule's stop record once its pilots found the plateau, before the
    # models train (`wgs all` prints the estimate of the rest with it)
    pilots_found: Callable[[dict], None] | None = None


# run(ws, cfg, env, force) -> False when the stage was up to date and skipped (ws: a `Workspace`)
Run = Callable[[Any, Any, StageEnv, bool], bool]
# cost(calibration, every stage's settings by name, the scene, the seconds modelled for the
# stages before it by name) -> what the stage is modelled to take
Cost = Callable[[Calibration, Mapping[str, Any], SceneFacts, Mapping[str, float]], StageCost]


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline. `name` keys the workspace (manifests, `Workspace.stage_dir`), its
    settings' table in a config file and, with '-' for '_', its `wgs` command; `folder` is its
    folder in the workspace, numbered in the method's order so that a listing shows it;
    `settings` its settings dataclass (the fields with a meaning are its command's options, in
    their order); `upstream` the stages whose outputs it reads (their fingerprints make it stale);
    `run` its run function; `outputs` what it writes for others to read (key -> path in its
    folder; readers ask `Workspace.output(stage, key)`); `cost` its model for the estimate;
    `presets` its settings under each preset (`config.PRESET_NAMES`); `all_options` its options
    that `wgs all` offers too; `trains_for` the stages whose time it trains for (the baseline);
    `method` False for what only measures, `on_request` True for what runs only when asked for."""

    name: str
    folder: str
    settings: type
    upstream: tuple[str, ...]
    run: Run
    help: str
    cost: Cost
    outputs: dict[str, str] = field(default_factory=dict)
    presets: dict[str, dict[str, Any]] = field(default_factory=dict)
    all_options: tuple[str, ...] = ()
    trains_for: tuple[str, ...] = ()
    method: bool = True
    on_request: bool = False

    @property
    def command(self) -> str:
        return self.name.replace("_", "-")

    @property
    def options(self) -> tuple[str, ...]:
        """The settings' fields that have a meaning on the command line, in their order."""
        return tuple(f.name for f in dataclasses.fields(self.settings) if facts(self.settings, f.name).get("help"))


# a trained model's outputs, the same for every stage that trains one
MODEL_OUTPUTS = {
    "model": "ckpt.pt",  # the model (normalised world) and its iteration
    "ply": "point_cloud.ply",  # the model in the INRIA layout, world coordinates
    "curve": "curve.json",  # test PSNR / SSIM on probe views against training time (curves.py)
}

# The fast preset (`make demo`'s budgets) of every 3DGS training stage: a few hundred iterations
# leave no room for a half-size phase (docs/speed.md)
FAST_TRAINING = {
    "refine_start": 100,
    "refine_every": 50,
    "sh_degree": 1,
    "sh_increase_every": 200,
    "init_points": 3000,
    "hull_resolution": 64,
    "max_gaussians": 20000,
    "floater_every": 200,
    "half_size_until": 0.0,
}


@dataclass
class CurveConfig:
    """Quality against time inside a training loop (curve.json): test PSNR / SSIM on a few fixed test
    views every so many training seconds (the probe's own time is left out of the clock)."""

    curve_every_s: float = 5.0  # 0: no curve
    curve_views: int = 4
    curve_points: int = 6  # and a probe at least every iterations / curve_points (short runs, fast machines)


@dataclass
class LpipsWeightsConfig:
    """Where LPIPS weights are looked for, the same for the fine stage's LPIPS term and eval."""

    lpips_weights: str | None = option(
        None, "Folder with LPIPS weights (else $WGS_LPIPS_WEIGHTS, $TORCH_HOME/hub/checkpoints).", metavar="DIR"
    )
