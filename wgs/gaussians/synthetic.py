"""A synthetic Gaussian cloud seen by one camera: what the rasterizer's tests, its benchmark and
the run-time calibration (`wgs.estimate`) render."""

from __future__ import annotations

import torch


def random_scene(n: int, size: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, ...]:
    """n Gaussians in a ball seen by one camera at distance 2.5 (footprints ~2-30 px at 256 px).

    Returns means [n, 3], quats [n, 4] (wxyz, unnormalised), scales [n, 3], opacities [n],
    colors [n, 3], viewmat [4, 4] (world-to-camera, OpenCV) and K [3, 3] of a `size` x `size` view.
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.5 - 4.0)
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[2, 3] = 2.5
    f = size * 1.2
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opac, colors, viewmat, K


def time_backend(
    backend: str,
    size: int,
    n: int,
    repeats: int,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> dict:
    """Seconds per forward and per forward + backward of `random_scene(n, size)` with rasterizer
    `backend` on `device`, after one untimed warm-up (numba loads its cache): {"forward",
    "forward_backward"}: {"median_s", "min_s", "max_s"}, and "repeats"."""
    import statistics
    import time

    from .render import rasterize

    device = torch.device(device)
    scene = tuple(t.to(device) for t in random_scene(n, size, dtype=dtype))
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1), dtype=dtype).to(device)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fwd, both = [], []
    for i in range(repeats + 1):
        means, quats, scales, opacities, colors = (t.detach().clone().requires_grad_(True) for t in scene[:5])
        t0 = time.perf_counter()
        rgb, alpha, _ = rasterize(
            means, quats, scales, opacities, colors, scene[5], scene[6], size, size, backend=backend
        )
        sync()
        t1 = time.perf_counter()
        ((rgb * weights).sum() + alpha.sum()).backward()
        sync()
        t2 = time.perf_counter()
        if i:
            fwd.append(t1 - t0)
            both.append(t2 - t0)

    def stats(xs: list[float]) -> dict[str, float]:
        return {"median_s": statistics.median(xs), "min_s": min(xs), "max_s": max(xs)}

    return {"forward": stats(fwd), "forward_backward": stats(both), "repeats": repeats}
