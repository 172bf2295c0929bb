"""Initial points: the visual hull of the training masks, or a fallback without masks; kNN scales;
statistical floater removal."""

from __future__ import annotations

import torch

from ..errors import InputError


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[N, 3] -> pixel coordinates [N, 2] (pixel centres at +0.5) and depth [N]."""
    p = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = p[:, 2]
    uv = (p @ K.T)[:, :2] / z.clamp_min(1e-9)[:, None]
    return uv, z


def visual_hull(frames, resolution: int = 96, extent: float = 1.0, max_points: int = 20000,
                near: float = 0.01, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Carve a grid over [-extent, extent]^3 (normalised world) with the training masks.

    A voxel is kept when, in all views (or all but one, with 3 or more views), it is in front of the
    camera, inside the frustum and inside the mask. A coarse pass finds the hull's bounding box and
    a second pass carves that box at `resolution`. Only the hull's surface voxels are returned
    (the renders see surfaces), coloured by the mean colour of the views that see them.

    Returns points [M, 3] and colours [M, 3]; raises InputError if the hull is empty.
    """
    lo = torch.full((3,), -extent)
    hi = torch.full((3,), extent)
    coarse = 32
    occ, _, grid = _carve(frames, lo, hi, coarse, near)
    if occ.any():
        pts = grid[occ.reshape(-1)]
        cell = (hi - lo) / coarse
        lo, hi = torch.maximum(pts.min(0).values - cell, lo), torch.minimum(pts.max(0).values + cell, hi)
    return _hull_surface(frames, lo, hi, resolution, near, max_points, generator)


def _carve(frames, lo: torch.Tensor, hi: torch.Tensor, resolution: int, near: float):
    """Occupancy [R, R, R], mean colours [R³, 3] and voxel centres [R³, 3] over the box lo..hi."""
    axes = [(torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * (hi[i] - lo[i]) + lo[i]
            for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    votes = torch.zeros(grid.shape[0], dtype=torch.int32)
    col_sum = torch.zeros(grid.shape[0], 3)
    col_n = torch.zeros(grid.shape[0])
    for f in frames:
        uv, z = project_points(grid, f.viewmat, f.K)
        u = torch.floor(uv[:, 0]).long()
        v = torch.floor(uv[:, 1]).long()
        inside = (z > near) & (u >= 0) & (u < f.width) & (v >= 0) & (v < f.height)
        idx = torch.where(inside, v * f.width + u, torch.zeros_like(u))
        in_mask = inside & (f.mask.reshape(-1)[idx] > 0.5)
        votes += in_mask.int()
        col_sum += torch.where(in_mask[:, None], f.image.reshape(-1, 3)[idx], torch.zeros(1, 3))
        col_n += in_mask.float()
    n = len(frames)
    need = n - 1 if n >= 3 else n
    occ = (votes >= need).reshape(resolution, resolution, resolution)
    return occ, col_sum / col_n.clamp_min(1)[:, None], grid


def _hull_surface(frames, lo, hi, resolution, near, max_points, generator):
    occ, colours, grid = _carve(frames, lo, hi, resolution, near)
    if not occ.any():
        raise InputError("the visual hull of the training masks is empty: the training views share no object "
                         "region. Check that the masks are white on the object, that every training view sees it, "
                         "and that the poses are right (camera-to-world vs world-to-camera, OpenGL vs OpenCV axes)")
    pad = torch.nn.functional.pad(occ[None, None].float(), (1, 1, 1, 1, 1, 1))
    interior = -torch.nn.functional.max_pool3d(-pad, 3, stride=1)[0, 0] > 0.5
    surface = (occ & ~interior).reshape(-1)
    pts = grid[surface]
    cols = colours[surface]
    jitter = (torch.rand(pts.shape, generator=generator) - 0.5) * ((hi - lo) / resolution)
    pts = pts + jitter
    if pts.shape[0] > max_points:
        keep = torch.randperm(pts.shape[0], generator=generator)[:max_points]
        pts, cols = pts[keep], cols[keep]
    return pts, cols


def random_init(n: int, radius: float = 0.5, generator: torch.Generator | None = None
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
        d = torch.cdist(points[i:i + chunk], points)
        out.append(d.topk(k + 1, largest=False).values[:, 1:].mean(dim=1))
    return torch.cat(out)


def floater_mask(means: torch.Tensor, k: int = 8, lam: float = 3.0) -> torch.Tensor:
    """True for Gaussians whose mean kNN distance exceeds mean + lam * std (GaussianObject)."""
    if means.shape[0] <= k + 1:
        return torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    d = knn_mean_distance(means.detach(), k)
    return d > d.mean() + lam * d.std()
