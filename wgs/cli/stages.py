"""The stages' commands, one per registry stage (made from it), and `wgs all`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from ..config import AllConfig
from ..context import RunOptions
from ..errors import WgsError
from ..fields import option
from ..progress import log
from ..stages.registry import REGISTRY, STAGE
from ..stages.stage import Stage
from .main import stage_common
from .options import all_options, all_overrides, config_options, settings_options


def _prepare(obj: RunOptions, scene: Path, force, preset, **options) -> None:
    from ..pipeline import prepare_and_estimate

    prepare_and_estimate(obj, scene, preset, options, force)


_prepare.__doc__ = STAGE["prepare"].help
prepare = click.command("prepare")(
    click.argument("scene", type=click.Path(path_type=Path))(
        config_options("prepare", *STAGE["prepare"].options)(stage_common(click.pass_obj(_prepare)))
    )
)


def stage_command(stage: Stage) -> click.Command:
    """`wgs <stage>`: the stage's options (`Stage.options`), --force, --preset and -w."""

    def run(obj: RunOptions, force: bool, preset: str | None, **options) -> None:
        env: dict[str, Any] = {}
        if stage.name == "eval":  # the newest model: fine, or coarse when the repair stages were left out
            from ..stages.shared import newest_model

            env["final"] = newest_model(obj.ws())
        obj.run(stage.name, obj.config(stage.name, preset, **options), force, **env)

    run.__doc__ = stage.help
    f = click.pass_obj(run)
    f = stage_common(f)
    f = config_options(stage.name, *stage.options)(f)
    return click.command(stage.command)(f)


STAGE_COMMANDS = tuple(stage_command(s) for s in REGISTRY[1:])  # the first, prepare, takes the scene


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
