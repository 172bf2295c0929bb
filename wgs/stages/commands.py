"""Click commands of the training stages (kept apart from cli.py so heavy imports stay lazy)."""

from __future__ import annotations


def register(cli, stage_common, workspace_option) -> None:  # noqa: ARG001
    """Add the stage subcommands to the `wgs` group."""
