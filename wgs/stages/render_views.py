"""`wgs render`: PNGs of a trained model at the train, test or an orbit path of cameras."""

from __future__ import annotations

import torch

from ..errors import InputError
from ..gaussians.splats import load_checkpoint
from ..gaussians.trainer import render_frame
from ..io.images import write_gif, write_png
from ..progress import log
from ..scene.dataset import load_prepared
from ..scene.orbit import orbit_frames
from ..workspace import Workspace
from .shared import background_for


def run_render(ws: Workspace, stage: str, views: str, n_frames: int, device: torch.device, video: bool = False) -> None:
    if ws.manifest(stage) is None:
        raise InputError(f"stage '{stage}' has not run yet", ws.stage_dir(stage))
    scene = load_prepared(ws.output("prepare", "prepared"))
    splats, _ = load_checkpoint(ws.output(stage, "model"), scene.norm, device)
    frames = {"train": scene.train, "test": scene.test, "path": orbit_frames(scene.train, n_frames)}[views]
    out = ws.root / "renders" / f"{stage}_{views}"
    bg = background_for(scene)
    images = []
    for f in frames:
        rgb, _ = render_frame(splats, f, device, bg)
        write_png(out / f.name, rgb.numpy())
        images.append(rgb.numpy())
    log(f"render: {len(frames)} images in {out}")
    if video:
        write_gif(out.with_suffix(".gif"), images)
        log(f"render: animation {out.with_suffix('.gif')}")
