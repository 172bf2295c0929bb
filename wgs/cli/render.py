"""`wgs render`: a trained model's renders as PNGs (and a GIF)."""

from __future__ import annotations

from dataclasses import dataclass

import click

from ..fields import option
from .main import workspace_option
from .options import ModelChoice, settings_options


@dataclass
class RenderSettings(ModelChoice):
    views: str = option("test", "Cameras to render.", choices=("test", "train", "path"))
    frames: int = option(60, "Number of frames for --views path.")
    video: bool = option(False, "Also write the frames as an animated GIF (a turntable with --views path).")


@click.command()
@settings_options(RenderSettings)
@workspace_option
@click.pass_obj
def render(obj, stage, views, frames, video):
    """Render a trained model to PNGs under WS/renders/STAGE_VIEWS/."""
    from ..stages.render_views import run_render
    from ..stages.shared import newest_model

    ws = obj.ws()
    run_render(ws, stage or newest_model(ws), views, frames, obj.torch_device(), video)
