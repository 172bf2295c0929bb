"""Click commands of the training stages (kept apart from cli.py so heavy imports stay lazy)."""

from __future__ import annotations

import click


def register(cli, stage_common, workspace_option) -> None:
    """Add the stage subcommands to the `wgs` group."""

    @cli.command()
    @click.option("--iterations", type=int, default=None, help="Training iterations.")
    @click.option("--max-seconds", type=float, default=None, help="Stop training after this many seconds.")
    @click.option("--sh-degree", type=int, default=None, help="Spherical-harmonics degree (0-3).")
    @stage_common
    @click.pass_obj
    def coarse(obj, iterations, max_seconds, sh_degree, force, preset):
        """Train the coarse 3DGS G_c on the training views."""
        from .s1_coarse import run_coarse

        cfg = obj.config("coarse", preset, iterations=iterations, max_seconds=max_seconds, sh_degree=sh_degree)
        if not 0 <= cfg.sh_degree <= 3:
            raise click.BadParameter(f"SH degree must be 0..3, got {cfg.sh_degree}", param_hint="--sh-degree")
        run_coarse(obj.ws(), cfg, obj.torch_device(), obj.seed, force=force)

    @cli.command()
    @click.option("--stage", "stage", type=click.Choice(["coarse"]), default="coarse", help="Which model.")
    @click.option("--views", type=click.Choice(["test", "train", "path"]), default="test", help="Cameras to render.")
    @click.option("--frames", type=int, default=60, help="Number of frames for --views path.")
    @workspace_option
    @click.pass_obj
    def render(obj, stage, views, frames):
        """Render a trained model to PNGs under WS/renders/STAGE_VIEWS/."""
        from .render_views import run_render

        run_render(obj.ws(), stage, views, frames, obj.torch_device())
