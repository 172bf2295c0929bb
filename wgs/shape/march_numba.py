"""CPU fast path of `hull.silhouette_torch`: each pixel's ray marched through the occupancy grid
at the same samples, stopping at the first occupied voxel (the reference samples every ray to the
end of the box)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def first_hit(occ, res, lo, cell, origin, dirs, t_in, t_out, dt):
    """occ [R³] uint8 (x-major), lo / cell [3], origin [3], dirs [P, 3], t_in / t_out / dt [P]
    -> depth [P] of the first occupied sample t_in + (k + 0.5) dt <= t_out, inf where none."""
    n = dirs.shape[0]
    out = np.full(n, np.inf, dtype=np.float32)
    for p in nb.prange(n):
        k = 0
        while True:
            t = t_in[p] + (k + 0.5) * dt[p]
            if t > t_out[p]:
                break
            i = int(math.floor((origin[0] + t * dirs[p, 0] - lo[0]) / cell[0]))
            j = int(math.floor((origin[1] + t * dirs[p, 1] - lo[1]) / cell[1]))
            m = int(math.floor((origin[2] + t * dirs[p, 2] - lo[2]) / cell[2]))
            if 0 <= i < res and 0 <= j < res and 0 <= m < res and occ[(i * res + j) * res + m]:
                out[p] = t
                break
            k += 1
    return out
