"""What the silhouette model S sees at a pose, computed the same way for its training pairs
(`prior.pairs`) and in the pipeline: the coarse model's render and opacity, the visual hull's
silhouette and its depth relative to the hull's centre. S runs at its own working size
(`SilhouetteNetConfig.work_size`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..models.storage import config_of
from ..scene.camera import Camera
from .hull import HullGrid, silhouette

CHANNELS = 6


def hull_channels(grid: HullGrid, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """The hull's silhouette [H, W] (0/1) and depth [H, W]: (depth - the box centre's depth) / half
    the box's diagonal where covered, 0 elsewhere."""
    cover, depth = silhouette(grid, camera)
    centre = 0.5 * (grid.lo + grid.hi)
    centre_z = float(centre @ camera.viewmat[2, :3] + camera.viewmat[2, 3])
    half_diag = 0.5 * float((grid.hi - grid.lo).norm())
    rel = torch.where(cover, (depth - centre_z) / half_diag, torch.zeros_like(depth))
    return cover.float(), rel


def silhouette_inputs(
    rgb: torch.Tensor, alpha: torch.Tensor, hull: torch.Tensor, hull_depth: torch.Tensor
) -> torch.Tensor:
    """rgb [H, W, 3], alpha [H, W], hull [H, W], hull_depth [H, W] -> S's input [6, H, W]."""
    return torch.cat([rgb.permute(2, 0, 1), alpha[None], hull[None], hull_depth[None]], 0).float()


def to_work_size(x: torch.Tensor, size: int) -> torch.Tensor:
    """[B, C, H, W] resized (area-filtered when shrinking) so that the longer side is `size`."""
    h, w = x.shape[-2:]
    scale = size / max(h, w)
    if abs(scale - 1) < 1e-6:
        return x
    return F.interpolate(
        x,
        size=(max(1, round(h * scale)), max(1, round(w * scale))),
        mode="bilinear",
        align_corners=False,
        antialias=scale < 1,
    )


@torch.no_grad()
def predict_object(model: torch.nn.Module, inputs: torch.Tensor) -> torch.Tensor:
    """S's object probability [H, W] for inputs [6, H, W]: run at S's working size, resized back."""
    return predict_batch(model, inputs[None])[0]


@torch.no_grad()
def predict_batch(model: torch.nn.Module, inputs: torch.Tensor) -> torch.Tensor:
    """S's object probability [B, H, W] for inputs [B, 6, H, W]."""
    h, w = inputs.shape[-2:]
    dev = next(model.parameters()).device
    prob = torch.sigmoid(model(to_work_size(inputs, config_of(model).work_size).to(dev))).cpu()
    if prob.shape[-2:] != (h, w):
        prob = F.interpolate(prob, size=(h, w), mode="bilinear", align_corners=False)
    return prob[:, 0]
