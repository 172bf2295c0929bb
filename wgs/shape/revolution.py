"""Solids of revolution: the largest one about an axis inside an occupancy grid, and the axes to try.

Bottles, cups, vases, bowls, lamps and turned wood are solids of revolution. The hull of a few
photos of one is polygonal across its axis (a square for 4 photos 90 degrees apart, 27 % more area
than the circle); the largest solid of revolution inside that hull is round again. `own_shape` keeps
it only where the photos' masks allow it."""

from __future__ import annotations

import math

import torch

from ..scene.orbit import fit_orbit
from .hull import HullGrid

ANGLES = 24  # rotations about the axis a voxel's centre must survive (every 15 degrees)


def rotation_matrices(axis: torch.Tensor, angles: int) -> torch.Tensor:
    """[angles, 3, 3]: rotations by k * 360 / angles degrees about the unit `axis` [3] (Rodrigues)."""
    a = torch.nn.functional.normalize(axis.double(), dim=0)
    k = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    theta = torch.arange(angles, dtype=torch.float64) * (2 * math.pi / angles)
    eye = torch.eye(3, dtype=torch.float64)
    return (eye + torch.sin(theta)[:, None, None] * k + (1 - torch.cos(theta))[:, None, None] * (k @ k)).float()


def spread_order(n: int) -> list[int]:
    """0..n-1 ordered so that each next index lies far from those before it (0, n/2, n/4, 3n/4, ...)."""
    order, step = [0], n
    while len(order) < n:
        step = max(step // 2, 1)
        order += [k for k in range(0, n, step) if k not in order]
    return order


def _revolution_inputs(grid: HullGrid, point: torch.Tensor, axis: torch.Tensor, angles: int):
    """What `revolved` works on: the occupancy grown by one voxel [R³] bool, the occupied voxels'
    flat indices [N] and centres less `point` [N, 3], the rotations in the order tried [A - 1, 3, 3]
    (far-apart angles first: most voxels that go, go early)."""
    grown = torch.nn.functional.max_pool3d(grid.occ[None, None].float(), 3, stride=1, padding=1)[0, 0].reshape(-1) > 0
    idx = grid.occ.reshape(-1).nonzero()[:, 0]
    rots = rotation_matrices(axis, angles)[spread_order(angles)[1:]]
    return grown, idx, grid.centres()[idx] - point, rots


def revolved_torch(grid: HullGrid, point: torch.Tensor, axis: torch.Tensor, angles: int = ANGLES) -> HullGrid:
    """The reference of `revolved`: the voxels still in the running turned by one angle at a time."""
    grown, idx, rel, rots = _revolution_inputs(grid, point, axis, angles)
    for rot in rots:
        vox = grid.voxel_index(rel @ rot.T + point)
        keep = (vox >= 0) & grown[vox.clamp_min(0)]
        idx, rel = idx[keep], rel[keep]
    out = torch.zeros(grid.occ.numel(), dtype=torch.bool)
    out[idx] = True
    return grid.with_occupancy(out)


def revolved(grid: HullGrid, point: torch.Tensor, axis: torch.Tensor, angles: int = ANGLES) -> HullGrid:
    """The occupied voxels whose centre stays within one voxel of an occupied voxel under every
    rotation by a multiple of 360 / `angles` degrees about the line through `point` [3] along `axis`
    [3]: the largest solid of revolution about that line inside the grid (the one voxel of slack
    keeps the grid's own steps from eating its outline). CPU numba kernel (`revolution_numba`);
    `revolved_torch` is its reference."""
    from .revolution_numba import kept_under_rotations

    grown, idx, rel, rots = _revolution_inputs(grid, point, axis, angles)
    keep = kept_under_rotations(
        rel.float().contiguous().numpy(),
        point.float().contiguous().numpy(),
        rots.float().contiguous().numpy(),
        grid.lo.float().contiguous().numpy(),
        grid.cell.float().contiguous().numpy(),
        grid.resolution,
        grown.to(torch.uint8).numpy(),
    )
    out = torch.zeros(grid.occ.numel(), dtype=torch.bool)
    out[idx[torch.from_numpy(keep)]] = True
    return grid.with_occupancy(out)


def candidate_axes(grid: HullGrid, photos) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    """Lines to try, each (name, point [3], unit direction [3]) through the occupied voxels'
    centroid: the photos' mean up direction (objects stand upright in most captures) and the
    occupancy's three principal axes (smallest variance first)."""
    pts = grid.centres()[grid.occ.reshape(-1)]
    centroid = pts.mean(0)
    up = torch.from_numpy(fit_orbit(photos).up).float()
    _, vecs = torch.linalg.eigh(torch.cov((pts - centroid).T.double()))
    axes = [("upright axis", up)] + [(f"principal axis {i + 1}", vecs[:, i].float()) for i in range(3)]
    return [(name, centroid, torch.nn.functional.normalize(a, dim=0)) for name, a in axes if float(a.norm()) > 1e-6]


def shifted(point: torch.Tensor, axis: torch.Tensor, step: float, reach: int = 1) -> list[torch.Tensor]:
    """Points around `point` [3] across `axis` [3]: offsets of k * step along two directions
    perpendicular to it, k in -reach..reach ((2 reach + 1)² points, `point` first)."""
    helper = torch.zeros(3)
    helper[int(axis.abs().argmin())] = 1.0
    t1 = torch.nn.functional.normalize(torch.linalg.cross(axis, helper), dim=0)
    t2 = torch.linalg.cross(axis, t1)
    ks = sorted(
        ((i, j) for i in range(-reach, reach + 1) for j in range(-reach, reach + 1)),
        key=lambda ij: abs(ij[0]) + abs(ij[1]),
    )
    return [point + step * (i * t1 + j * t2) for i, j in ks]
