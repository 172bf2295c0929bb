"""Initial points: the visual hull of the training masks, or a fallback without masks; kNN scales;
statistical floater removal."""

from __future__ import annotations

import torch

from ..shape.hull import HullGrid, mask_votes, surface, visual_hull_grid


def visual_hull(
    frames,
    resolution: int = 96,
    extent: float = 1.0,
    max_points: int = 20000,
    near: float = 0.01,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial points from the training masks' visual hull (`shape.hull.visual_hull_grid`, then
    `hull_points`). Returns points [M, 3] and colours [M, 3]; raises InputError if the hull is empty."""
    return hull_points(visual_hull_grid(frames, resolution, extent, near), frames, max_points, generator, near)


def hull_points(
    grid: HullGrid, frames, max_points: int, generator: torch.Generator | None = None, near: float = 0.01
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points [M, 3] on the surface of an occupancy grid (the renders see surfaces), jittered within
    their voxel, at most `max_points` of them, and their colours [M, 3]: the mean colour of the
    frames whose masks hold their voxel's centre."""
    keep = surface(grid)
    centres = grid.centres()[keep]
    pts = centres + (torch.rand(centres.shape, generator=generator) - 0.5) * grid.cell
    if pts.shape[0] > max_points:
        pick = torch.randperm(pts.shape[0], generator=generator)[:max_points]
        centres, pts = centres[pick], pts[pick]
    return pts, mask_votes(frames, centres, near)[1]


def random_init(
    n: int, radius: float = 0.5, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fallback without masks: points uniform in a ball around the object centre, grey."""
    d = torch.randn(n, 3, generator=generator)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-9)
    r = radius * torch.rand(n, 1, generator=generator) ** (1 / 3)
    return d * r, torch.full((n, 3), 0.5)


def knn_mean_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean distance of each point to its k nearest neighbours: [N, 3] -> [N] (a KD-tree, scipy's
    cKDTree: O(N log N); `knn_mean_distance_torch` is the O(N^2) reference)."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, device=points.device)
    from scipy.spatial import cKDTree

    k = min(k, n - 1)
    pts = points.detach().to("cpu", torch.float64).numpy()
    dist, _ = cKDTree(pts).query(pts, k + 1, workers=torch.get_num_threads())
    return torch.from_numpy(dist[:, 1:].mean(axis=1)).to(device=points.device, dtype=points.dtype)


def knn_mean_distance_torch(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    """Reference of `knn_mean_distance`: brute-force distances in chunks (any device)."""
    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, device=points.device)
    k = min(k, n - 1)
    out = []
    for i in range(0, n, chunk):
        d = torch.cdist(points[i : i + chunk], points)
        out.append(d.topk(k + 1, largest=False).values[:, 1:].mean(dim=1))
    return torch.cat(out)


def floater_mask(means: torch.Tensor, k: int = 8, lam: float = 3.0) -> torch.Tensor:
    """True for Gaussians whose mean kNN distance exceeds mean + lam * std (GaussianObject)."""
    if means.shape[0] <= k + 1:
        return torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    d = knn_mean_distance(means.detach(), k)
    return d > d.mean() + lam * d.std()
