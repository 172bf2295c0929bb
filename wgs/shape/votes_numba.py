"""CPU fast path of `hull.hull_votes_torch`: each point projected into the views one after another,
stopping once more masks leave it out than the hull allows (the reference does the same per view
on the points still in the running). Projection in float32 like the reference; a point within
float rounding of a pixel edge may land in the neighbouring pixel."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def hull_votes(points, viewmats, Ks, masks, offsets, widths, heights, allowed, off_frame, near):
    """points [N, 3] float32; per view f: viewmats[f] [4, 4], Ks[f] [3, 3] (float32), its mask as
    uint8 masks[offsets[f]:offsets[f] + widths[f] * heights[f]] (row-major, 1 = object).
    off_frame: what a view says of a point in front of it, outside its frame, whose nearest border
    pixel is object (0 abstains, 1 object, 2 background; see `hull.OFF_FRAME`)
    -> votes [N] int32: the masks that hold each point, -1 where more than `allowed` leave it out."""
    n, views = points.shape[0], viewmats.shape[0]
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
            hit, abstain = False, False
            if pz > near:
                w = max(pz, eps)
                u = np.floor((px * K[0, 0] + py * K[0, 1] + pz * K[0, 2]) / w)
                v = np.floor((px * K[1, 0] + py * K[1, 1] + pz * K[1, 2]) / w)
                outside = u < 0.0 or v < 0.0 or u > widths[f] - 1.0 or v > heights[f] - 1.0
                u = min(max(u, 0.0), widths[f] - 1.0)
                v = min(max(v, 0.0), heights[f] - 1.0)
                hit = masks[offsets[f] + int(v) * widths[f] + int(u)] != 0
                if outside and hit:  # the object runs out of this photo here
                    abstain = off_frame == 0
                    hit = off_frame == 1
            if hit:
                hits += 1
            elif not abstain:
                missed += 1
                if missed > allowed:
                    hits = -1
                    break
        votes[i] = hits
    return votes
