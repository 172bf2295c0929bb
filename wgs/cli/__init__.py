"""The `wgs` command line (click).

Pipeline: prepare -> coarse -> mask-data -> finetune -> repair -> fine -> eval.
Each stage reads and writes one workspace folder and is skipped when its inputs are unchanged.
The group and its global options are in `main`, each command in a module of its own; the stage
commands are made from the registry (`stages`). The commands are listed in this order.
"""

from .ablate import ablate
from .batch import batch
from .export import export
from .info import info
from .main import cli, main
from .render import render
from .stages import STAGE_COMMANDS, all_, prepare
from .suggest import suggest
from .view import view

for _command in (prepare, info, suggest, *STAGE_COMMANDS, all_, batch, ablate, render, view, export):
    cli.add_command(_command)

__all__ = ["cli", "main"]
