"""Morphological opening of an occupancy grid: the union of the balls of one radius that fit inside it.

A solid whose every point lies in a ball of radius r inside it (a vase, a bottle's body, anything
round at that scale) is left whole by the opening at r of any grid that contains it, while the
corners and wedges of a visual hull, which such a ball cannot reach, go. Thinner parts (a leg, a
handle, a neck) go too; `own_shape` gives back what the real masks need."""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from .hull import HullGrid


def inscribed_distance(grid: HullGrid) -> np.ndarray:
    """[R, R, R] float: for each voxel, the distance (normalised world) from its centre to the
    nearest empty voxel's centre, out past the grid's box counting as empty (0 where empty)."""
    occ = np.pad(grid.occ.numpy(), 1)
    return distance_transform_edt(occ, sampling=grid.cell.double().numpy())[1:-1, 1:-1, 1:-1]


def opening(grid: HullGrid, radius: float) -> HullGrid:
    """The grid's occupied voxels covered by a ball of `radius` (normalised world) whose centre is a
    voxel centre farther than `radius` from every empty voxel: the union of the balls that fit."""
    centres = np.pad(inscribed_distance(grid) > radius, 1)
    if not centres.any():
        return grid.with_occupancy(torch.zeros_like(grid.occ))
    reach = distance_transform_edt(~centres, sampling=grid.cell.double().numpy())[1:-1, 1:-1, 1:-1]
    return grid.with_occupancy(grid.occ & torch.from_numpy(reach <= radius))
