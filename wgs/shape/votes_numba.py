"""CPU fast path of `hull.hull_votes_torch`: each point projected into the views one after another,
stopping once it has missed more masks than the hull allows (the reference does the same per view
on the points still in the running). Projection in float32 like the reference; a point within
float rounding of a pixel edge may land in the neighbouring pixel."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def hull_votes(points, viewmats, Ks, masks, offsets, widths, heights, need, near):
    """points [N, 3] float32; per view f: viewmats[f] [4, 4], Ks[f] [3, 3] (float32), its mask as
    uint8 masks[offsets[f]:offsets[f] + widths[f] * heights[f]] (row-major, 1 = object)
    -> votes [N] int32, exact for every point that reaches `need`."""
    n, views = points.shape[0], viewmats.shape[0]
    allowed = views - need
    votes = np.zeros(n, dtype=np.int32)
    eps = np.float32(1e-9)
    for i in nb.prange(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        hits, missed = 0, 0
        for f in range(views):
            R, K = viewmats[f], Ks[f]
            px = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + R[0, 3]
            py = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + R[1, 3]
            pz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + R[2, 3]
            hit = False
            if pz > near:
                w = max(pz, eps)
                u = np.floor((px * K[0, 0] + py * K[0, 1] + pz * K[0, 2]) / w)
                v = np.floor((px * K[1, 0] + py * K[1, 1] + pz * K[1, 2]) / w)
                u = min(max(u, 0.0), widths[f] - 1.0)  # off the frame: the border pixel (hull.mask_lookup)
                v = min(max(v, 0.0), heights[f] - 1.0)
                hit = masks[offsets[f] + int(v) * widths[f] + int(u)] != 0
            if hit:
                hits += 1
            else:
                missed += 1
                if missed > allowed:
                    break
        votes[i] = hits
    return votes
