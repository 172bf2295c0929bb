"""`wgs ablate`: the paper's ablation."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click

from ..fields import option
from ..stages.registry import STAGE
from .main import workspace_option
from .options import config_options, preset_option, settings_options


@dataclass
class AblateSettings:
    rows: str = option("paper", "paper | all | comma-separated row names (an unknown name lists them).")
    repeats: int = option(1, "Runs per row (seeds seed..seed+K-1).", bounds=(1, None))


@click.command()
@click.argument("scene", type=click.Path(path_type=Path))
@settings_options(AblateSettings)
@config_options("prepare", *STAGE["prepare"].all_options)  # the scene's import, as `wgs all` offers it
@preset_option
@workspace_option
@click.pass_obj
def ablate(obj, scene, rows, repeats, preset, **prepare_options):
    """The paper's ablation on SCENE: one workspace per row under -w ROOT, and ROOT/ablation.{md,csv,json,png}.
    Every row trains on the same prepared views (--mirror none: the photos alone, as in the paper)."""
    from ..ablation import aggregate, parse_rows, run_ablation, write_outputs
    from ..progress import results

    root = obj.ws().root
    row_list = parse_rows(rows)
    records = run_ablation(obj, scene, root, row_list, repeats, preset, prepare_options)
    write_outputs(root, aggregate(records, row_list), records)
    results.print((root / "ablation.md").read_text())
