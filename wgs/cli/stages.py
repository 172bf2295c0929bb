"""The stages' commands: `wgs prepare`, one command per registry stage (made in a loop), and `wgs all`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from ..config import REGISTRY, AllConfig, Stage
from ..context import RunOptions
from ..errors import WgsError
from ..fields import option
from ..progress import log
from .main import stage_common
from .options import all_options, all_overrides, config_options, settings_options


@click.command()
@click.argument("scene", type=click.Path(path_type=Path))
@config_options(
    "prepare",
    "views",
    "downscale",
    "max_size",
    "max_pixels",
    "matcher",
    "focal",
    "fov",
    "cameras",
    "masks",
    "mask_agreement",
    "mask_voter_support",
    "mask_colour_ratio",
    "mask_max_cut",
    "mask_max_missed",
    "mirror",
)
@stage_common
@click.pass_obj
def prepare(obj: RunOptions, scene: Path, force, preset, **options) -> None:
    """Import SCENE (COLMAP, Blender, instant-ngp/nerfstudio, IDR, LLFF, or photos without poses,
    which structure-from-motion poses) into the workspace."""
    from ..pipeline import prepare_and_estimate

    prepare_and_estimate(obj, scene, preset, options, force)


# the options each stage's command offers, in the order its help lists them, and what it does
STAGE_OPTIONS: dict[str, tuple[str, ...]] = {
    "coarse": ("iterations", "max_seconds", "sh_degree", "ensemble", "stop"),
    "mask_data": ("strategy", "iterations", "n_regions", "coverage"),
    "finetune": (
        "domain",
        "use_u",
        "levels",
        "d_steps",
        "diffusion",
        "sd_model",
        "controlnet",
        "u_max_steps",
        "prior_steps",
        "prior",
    ),
    "repair": (
        "poses",
        "num_views",
        "strength",
        "steps",
        "views_per_train",
        "carve",
        "shape_revolution",
        "shape_smooth",
    ),
    "fine": ("iterations", "rounds", "lpips_weights", "start"),
    "eval": ("lpips_net", "lpips_weights", "max_views", "repair_gain_views", "localise_steps"),
    "baseline": (),
}
STAGE_HELP: dict[str, str] = {
    "coarse": "Train the coarse 3DGS G_c on the training views.",
    "mask_data": "Corrupted/clean pairs for the repair models (trains G_d, or N models for loo).",
    "finetune": "Fine-tune the repair model D (from the pretrained prior) and the HF U-Net U on this object.",
    "repair": "Render G_c at novel views and repair them with D and U -> pseudo references.",
    "fine": "Train G_f on the real and the pseudo references.",
    "eval": "PSNR, SSIM, LPIPS and silhouettes of G_f and G_c on the test views, and the error-against-time report.",
    "baseline": "Plain 3DGS trained for the pipeline's training time (what that time buys without the repair);\n"
    "eval then draws its curve beside the method's.",
}


def stage_command(stage: Stage) -> click.Command:
    """`wgs <stage>`: the stage's options (`STAGE_OPTIONS`), --force, --preset and -w."""

    def run(obj: RunOptions, force: bool, preset: str | None, **options) -> None:
        env: dict[str, Any] = {}
        if stage.name == "eval":  # the newest model: fine, or coarse when the repair stages were left out
            from ..stages.shared import newest_model

            env["final"] = newest_model(obj.ws())
        obj.run(stage.name, obj.config(stage.name, preset, **options), force, **env)

    run.__doc__ = STAGE_HELP[stage.table]
    f = click.pass_obj(run)
    f = stage_common(f)
    f = config_options(stage.table, *STAGE_OPTIONS[stage.table])(f)
    return click.command(stage.command)(f)


STAGE_COMMANDS = tuple(stage_command(s) for s in REGISTRY if s.name != "scene")


@dataclass
class AllRunSettings(AllConfig):
    """`wgs all`'s own options: the [all] table's (its click default None: the config file's
    `[all]` holds the default) and two that the config file does not take."""

    force_repair: bool = option(False, "Run the repair stages even with many training views.")
    baseline: bool = option(
        False, "Also train plain 3DGS for the same training time and plot its curve (wgs baseline)."
    )


@click.command("all")
@click.argument("scene", type=click.Path(path_type=Path))
@all_options
@settings_options(AllRunSettings)
@stage_common
@click.pass_obj
def all_(obj, scene, budget, force_repair, baseline, force, preset, **options):
    """Run every stage on SCENE (each skipped when up to date) and print the summary."""
    from ..pipeline import print_summary, run_all

    scene = Path(scene).resolve()  # messages name the folder, not "."
    if obj.workspace is None:  # beside the scene folder: SCENE_wgs (`wgs all .` too)
        if not scene.name:
            raise WgsError("no workspace name for the root folder: pass -w/--workspace DIR")
        obj.workspace = scene.with_name(scene.name + "_wgs")
        log(f"workspace: {obj.workspace}")
    from ..estimate import parse_duration

    budget = budget or obj.file_cfg.get("all", {}).get("budget")
    outcomes = run_all(
        obj,
        scene,
        preset,
        force,
        force_repair,
        all_overrides(options),
        ("baseline",) if baseline else (),
        parse_duration(budget) if budget else None,
    )
    print_summary(obj.ws(), outcomes)
