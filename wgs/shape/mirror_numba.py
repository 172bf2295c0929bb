"""CPU fast path of `symmetry.mirrored_occupancy` followed by `RayVoxels.iou`: for each plane and
each ray, the ray's voxels are mirrored one at a time until one lands in an occupied voxel, so a
plane costs about one lookup per covered pixel instead of one per voxel of the grid."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def mirror_ious(occ, res, lo, cell, centres, normals, offsets, ray_voxels, on_mask, mask_total):
    """occ [R³] uint8 (x-major), lo / cell [3], centres [R³, 3] of all voxels, planes normals [B, 3]
    and offsets [B], ray_voxels [P, K] occupied voxels per ray (-1 ends a row), on_mask [P] bool,
    mask_total (mask pixels among all sampled) -> silhouette IoU [B] of the occupied voxels whose
    mirror image is occupied."""
    n_planes = normals.shape[0]
    out = np.zeros(n_planes)
    for b in nb.prange(n_planes):
        n0, n1, n2 = normals[b, 0], normals[b, 1], normals[b, 2]
        inter = 0
        covered = 0
        for p in range(ray_voxels.shape[0]):
            for q in range(ray_voxels.shape[1]):
                v = ray_voxels[p, q]
                if v < 0:
                    break
                c0, c1, c2 = centres[v, 0], centres[v, 1], centres[v, 2]
                dist = c0 * n0 + c1 * n1 + c2 * n2 - offsets[b]
                i = int(math.floor((c0 - 2.0 * dist * n0 - lo[0]) / cell[0]))
                j = int(math.floor((c1 - 2.0 * dist * n1 - lo[1]) / cell[1]))
                m = int(math.floor((c2 - 2.0 * dist * n2 - lo[2]) / cell[2]))
                if 0 <= i < res and 0 <= j < res and 0 <= m < res and occ[(i * res + j) * res + m]:
                    covered += 1
                    inter += on_mask[p]
                    break
        out[b] = inter / max(mask_total + covered - inter, 1)
    return out
