"""What the volume model V sees: the strict visual hull's box resampled to a cube of R³ cells, with
per cell how deep its centre lies inside the training masks.

For each training view, a cell's centre projects to a pixel; its signed distance to that mask's
outline (positive inside) is divided by the mask's equivalent radius sqrt(area / pi), so that the
feature does not depend on image size or zoom. A visual hull's excess sits where the cell is barely
inside the masks that bound it: on wedges and corners that the views' cones leave. The channels are
the strict hull (min > 0), the smallest and second smallest scaled distances (clamped to
[-1, 1]), and the number of views / 8.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from ..models.storage import config_of
from .hull import HullGrid, grid_centres, pixel_lookup

CHANNELS = 4
BOX_MARGIN = 1.08  # the cube's side over the hull box's longest side


@dataclass
class VolumeBox:
    """The cube V works on: R³ cells over lo..hi (normalised world)."""

    lo: torch.Tensor
    hi: torch.Tensor
    resolution: int

    def centres(self) -> torch.Tensor:
        return grid_centres(self.lo, self.hi, self.resolution)


def cube_around(grid: HullGrid, resolution: int) -> VolumeBox:
    """The cube centred on the hull's box, its side BOX_MARGIN times the box's longest side."""
    centre, half = 0.5 * (grid.lo + grid.hi), 0.5 * BOX_MARGIN * float((grid.hi - grid.lo).max())
    return VolumeBox(centre - half, centre + half, resolution)


def scaled_mask_distance(mask: torch.Tensor) -> torch.Tensor:
    """[H, W] mask -> signed distance to its outline [H, W] (pixels, positive inside) over the
    mask's equivalent radius."""
    inside = mask.numpy() > 0.5
    sd = ndimage.distance_transform_edt(inside) - ndimage.distance_transform_edt(~inside)
    radius = max(float(np.sqrt(inside.sum() / np.pi)), 1.0)
    return torch.from_numpy((sd / radius).astype(np.float32))


def mask_distances(frames, points: torch.Tensor) -> torch.Tensor:
    """Scaled signed distance of each point [N, 3] in each frame's mask: [V, N] (-1 where a point
    falls outside the frame or behind the camera)."""
    out = torch.full((len(frames), points.shape[0]), -1.0)
    for i, f in enumerate(frames):
        inside, idx = pixel_lookup(f, points)
        d = scaled_mask_distance(f.mask).reshape(-1)[idx]
        out[i] = torch.where(inside, d, torch.full_like(d, -1.0))
    return out


def volume_inputs(frames, box: VolumeBox) -> torch.Tensor:
    """V's input [4, R, R, R] for the training frames (with masks) over the cube."""
    d = mask_distances(frames, box.centres()).clamp(-1.0, 1.0)
    two = torch.topk(d, min(2, d.shape[0]), dim=0, largest=False).values
    first, second = two[0], two[-1]
    r = box.resolution
    chans = [(first > 0).float(), first, second, torch.full_like(first, len(frames) / 8.0)]
    return torch.stack(chans).reshape(CHANNELS, r, r, r)


def volume_target(frames, box: VolumeBox) -> torch.Tensor:
    """[R, R, R] float: the hull of many frames' masks (the training target; 1 inside)."""
    d = mask_distances(frames, box.centres())
    r = box.resolution
    return (d.min(0).values > 0).float().reshape(r, r, r)


def sample_volume(values: torch.Tensor, box: VolumeBox, points: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of values [R, R, R] (indexed x, y, z) at points [N, 3] -> [N]; outside the cube 0."""
    uvw = (points - box.lo) / (box.hi - box.lo) * 2 - 1  # align_corners=False: cell centres
    g = uvw.flip(-1).reshape(1, -1, 1, 1, 3)  # grid_sample wants (x=W, y=H, z=D) for input [D, H, W]
    out = torch.nn.functional.grid_sample(
        values[None, None].float(), g, mode="bilinear", padding_mode="zeros", align_corners=False
    )
    return out.reshape(-1)


@torch.no_grad()
def occupied_probability(model: torch.nn.Module, frames, grid: HullGrid) -> torch.Tensor:
    """V's object probability [M] at the grid's occupied voxels (occ.nonzero order), from the
    training frames' masks over the cube around the grid's box."""
    box = cube_around(grid, config_of(model).resolution)
    dev = next(model.parameters()).device
    prob = torch.sigmoid(model(volume_inputs(frames, box)[None].to(dev)))[0, 0].cpu()
    return sample_volume(prob, box, grid.centres()[grid.occ.reshape(-1)])
