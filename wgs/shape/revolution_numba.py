"""CPU fast path of `revolution.revolved_torch`: each voxel turned through the angles one after
another, stopping at the first that leaves the grown occupancy (the reference does the same per
angle on the voxels still in the running). Rotation and voxel lookup in float32 like the
reference; a centre within float rounding of a voxel face may land in the neighbouring voxel."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def kept_under_rotations(rel, point, rots, lo, cell, res, grown):
    """rel [N, 3] float32 voxel centres less `point` [3]; rots [A, 3, 3] float32, applied in order;
    lo, cell [3] float32 of a res³ grid; grown [res³] uint8 (x-major) -> keep [N] bool: each centre
    lands in a grown voxel under every rotation."""
    n, angles = rel.shape[0], rots.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    for i in nb.prange(n):
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        ok = True
        for k in range(angles):
            R = rots[k]
            p = (
                x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + point[0],
                x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + point[1],
                x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + point[2],
            )
            a = int(math.floor((p[0] - lo[0]) / cell[0]))
            b = int(math.floor((p[1] - lo[1]) / cell[1]))
            c = int(math.floor((p[2] - lo[2]) / cell[2]))
            if not (0 <= a < res and 0 <= b < res and 0 <= c < res and grown[(a * res + b) * res + c]):
                ok = False
                break
        keep[i] = ok
    return keep
