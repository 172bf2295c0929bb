"""Render 3D Gaussians: projection -> colour (SH) -> rasterization, as pure functions on tensors.

Backends for the pixel stage: "numba" (CPU fast path), "torch" (reference, any device) and
"gsplat" (CUDA, optional). "auto" picks gsplat on CUDA when installed, numba on the CPU, else torch.
"""

from __future__ import annotations

import functools
from typing import Any

import torch
from torch.profiler import record_function

from ..scene.camera import camera_center
from .project import project_gaussians
from .project_numba import project_gaussians_numba
from .raster_torch import rasterize_pixels_torch
from .sh import eval_sh, sh_degree_of


@functools.cache
def _has_gsplat() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def pick_backend(device: torch.device, backend: str = "auto") -> str:
    if backend != "auto":
        return backend
    if device.type == "cuda" and _has_gsplat():
        return "gsplat"
    return "numba" if device.type == "cpu" else "torch"


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    sh_degree: int | None = None,
    render_depth: bool = False,
    backend: str = "auto",
    near: float = 0.01,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render one view.

    Args:
        means [N, 3]; quats [N, 4] wxyz (unnormalised ok); scales [N, 3] (activated, > 0);
        opacities [N] in [0, 1]; colors [N, 3] (RGB) or sh [N, K, 3] with K = (degree + 1)^2;
        viewmat [4, 4] world-to-camera (OpenCV); K [3, 3]; background [3] (default black).
        sh_degree: SH degree to use (default: all of K).
    Returns:
        rgb [H, W, 3], alpha [H, W, 1], meta with "means2d" [N, 2] (retains grad: densification reads
        its gradient), "radii" [N] (px, 0 when culled), "visible" [N], "depths" [N], and
        "depth" [H, W, 1] (alpha-weighted expected depth) when render_depth.
    """
    n = means.shape[0]
    for name, t, shape in (
        ("means", means, (n, 3)),
        ("quats", quats, (n, 4)),
        ("scales", scales, (n, 3)),
        ("opacities", opacities, (n,)),
        ("viewmat", viewmat, (4, 4)),
        ("K", K, (3, 3)),
    ):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
    if background is None:
        background = torch.zeros(3, device=means.device, dtype=means.dtype)
    backend = pick_backend(means.device, backend)
    if backend == "gsplat":
        return _rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree, render_depth
        )
    # the numba projection differentiates means, quats and scales only; a camera being optimised
    # takes the reference
    fast_proj = backend == "numba" and not (viewmat.requires_grad or K.requires_grad)
    with record_function("wgs:project"):
        proj = (project_gaussians_numba if fast_proj else project_gaussians)(
            means, quats, scales, viewmat, K, width, height, near=near
        )
    if colors.dim() == 3:
        with record_function("wgs:sh"):
            deg = sh_degree_of(colors.shape[1]) if sh_degree is None else sh_degree
            campos = camera_center(viewmat)
            rgb_g = torch.clamp_min(eval_sh(colors, means - campos, deg) + 0.5, 0.0)
    else:
        rgb_g = colors
    feats, bg = rgb_g, background.to(means.dtype)
    if render_depth:
        feats = torch.cat([rgb_g, proj.depths[:, None].to(rgb_g.dtype)], dim=1)
        bg = torch.cat([bg, bg.new_zeros(1)])
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    raster = _rasterize_numba if backend == "numba" else rasterize_pixels_torch
    with record_function("wgs:raster"):
        out, alpha = raster(
            means2d, proj.conics, feats, opacities, proj.depths, proj.extents, proj.visible, width, height, bg
        )
    meta: dict[str, Any] = {
        "means2d": means2d,
        "radii": proj.extents.max(dim=1).values,
        "visible": proj.visible,
        "depths": proj.depths,
        "width": width,
        "height": height,
    }
    if render_depth:
        meta["depth"] = out[..., 3:4]
        out = out[..., :3]
    return out, alpha, meta


def _rasterize_numba(*args):
    from .raster_numba import rasterize_pixels_numba

    return rasterize_pixels_numba(*args)


def _rasterize_gsplat(
    means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree, render_depth
):  # pragma: no cover - CUDA only
    """gsplat's CUDA kernels (optional extra `wgs[cuda]`); same conventions as ours."""
    from gsplat import rasterization

    is_sh = colors.dim() == 3
    rc, ra, info = rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmat[None],
        K[None],
        width,
        height,
        sh_degree=(sh_degree if sh_degree is not None else sh_degree_of(colors.shape[1])) if is_sh else None,
        backgrounds=background[None],
        render_mode="RGB+ED" if render_depth else "RGB",
        packed=False,
    )
    meta = {
        "means2d": info["means2d"][0],
        "radii": info["radii"][0].float().amax(-1) if info["radii"].dim() == 3 else info["radii"][0].float(),
        "visible": (info["radii"][0] > 0).reshape(means.shape[0], -1).any(-1),
        "depths": info["depths"][0],
        "width": width,
        "height": height,
    }
    if info["means2d"].requires_grad:
        info["means2d"].retain_grad()
        meta["means2d"] = info["means2d"]
        meta["means2d_batched"] = True
    out = rc[0]
    if render_depth:
        meta["depth"] = out[..., 3:4]
        out = out[..., :3]
    return out, ra[0], meta
