"""`wgs render`: PNGs of a trained model at the train, test or an orbit path of cameras."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import InputError
from ..gaussians.splats import load_checkpoint
from ..gaussians.trainer import render_frame
from ..progress import log
from ..scene.dataset import Frame, load_prepared
from ..scene.images import write_png
from ..workspace import Workspace
from .s1_coarse import CKPT, background_for

STAGE_CKPT = {"coarse": ("coarse", CKPT)}


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (OpenCV: x right, y down, z forward) looking from eye at target."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def orbit_frames(train: list[Frame], n: int) -> list[Frame]:
    """n cameras on the circle fitted to the training cameras, looking at the object centre."""
    centers = np.stack([f.center.double().numpy() for f in train])
    ups = np.stack([-f.viewmat[1, :3].double().numpy() for f in train])  # camera -y is up
    up = ups.mean(0)
    up /= np.linalg.norm(up)
    height = float((centers @ up).mean())
    radius = float(np.linalg.norm(centers - np.outer(centers @ up, up), axis=1).mean())
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    f0 = train[0]
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = up * height + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        w2c = look_at(eye, np.zeros(3), up)
        out.append(Frame(f"path_{i:03d}.png", f0.K.clone(), torch.tensor(w2c, dtype=torch.float32), f0.width,
                         f0.height))
    return out


def run_render(ws: Workspace, stage: str, views: str, n_frames: int, device: torch.device) -> None:
    src, ckpt = STAGE_CKPT[stage]
    if ws.manifest(src) is None:
        raise InputError(f"stage '{stage}' has not run yet", ws.stage_dir(src))
    scene = load_prepared(ws)
    splats, _ = load_checkpoint(ws.stage_dir(src) / ckpt, scene.norm, device)
    frames = {"train": scene.train, "test": scene.test, "path": orbit_frames(scene.train, n_frames)}[views]
    out = ws.root / "renders" / f"{stage}_{views}"
    bg = background_for(scene)
    for f in frames:
        rgb, _ = render_frame(splats, f, device, bg)
        write_png(out / f.name, rgb.numpy())
    log(f"render: {len(frames)} images in {out}")
