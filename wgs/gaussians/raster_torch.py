"""Pure-torch reference rasterizer of projected 2D Gaussians (readable, autograd, any device).

Semantics shared with the numba fast path (tests compare the two):
  power = -0.5 (a dx² + c dy²) - b dx dy, with d = pixel centre (x + 0.5, y + 0.5) - mean2d;
  a Gaussian touches a pixel only inside its 3-sigma ellipse (-4.5 <= power <= 0);
  alpha = min(0.99, opacity · exp(power)), skipped below 1/255;
  front-to-back by depth, a Gaussian is blended only while the transmittance after it stays >= 1e-4.
"""

from __future__ import annotations

import torch

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
POWER_MIN = -4.5  # 3 sigma


def depth_order(depths: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Indices of the visible Gaussians, front to back (stable)."""
    idx = torch.nonzero(visible, as_tuple=False).squeeze(1)
    return idx[torch.argsort(depths[idx], stable=True)]


def rasterize_pixels_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    extents: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor,
    block: int = 32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite 2D Gaussians.

    Args:
        means2d [N, 2], conics [N, 3], colors [N, D], opacities [N], depths [N], extents [N, 2],
        visible [N] bool, background [D].
    Returns:
        color [H, W, D] (background composited) and alpha [H, W, 1].
    """
    order = depth_order(depths, visible)
    m, q, col, op, ext = means2d[order], conics[order], colors[order], opacities[order], extents[order]
    D = colors.shape[1]
    dev, dt = means2d.device, means2d.dtype
    # keeps the output attached to the graph when no Gaussian touches a block (zero gradient, not none)
    link = 0.0 * (means2d.sum() + conics.sum() + colors.sum() + opacities.sum())
    rows = []
    alpha_rows = []
    for y0 in range(0, height, block):
        y1 = min(height, y0 + block)
        row, arow = [], []
        for x0 in range(0, width, block):
            x1 = min(width, x0 + block)
            sel = (
                (m[:, 0] + ext[:, 0] >= x0)
                & (m[:, 0] - ext[:, 0] <= x1)
                & (m[:, 1] + ext[:, 1] >= y0)
                & (m[:, 1] - ext[:, 1] <= y1)
            )
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1, device=dev, dtype=dt) + 0.5,
                torch.arange(x0, x1, device=dev, dtype=dt) + 0.5,
                indexing="ij",
            )
            npx = ys.numel()
            if not bool(sel.any()):
                row.append(background.expand(npx, D).reshape(y1 - y0, x1 - x0, D).to(dt) + link)
                arow.append(torch.zeros(y1 - y0, x1 - x0, 1, device=dev, dtype=dt) + link)
                continue
            ms, qs, cs, os_ = m[sel], q[sel], col[sel], op[sel]
            dx = xs.reshape(-1, 1) - ms[None, :, 0]
            dy = ys.reshape(-1, 1) - ms[None, :, 1]
            power = -0.5 * (qs[None, :, 0] * dx * dx + qs[None, :, 2] * dy * dy) - qs[None, :, 1] * dx * dy
            inside = (power <= 0) & (power >= POWER_MIN)
            raw = os_[None, :] * torch.exp(power.clamp(max=0.0))
            al = torch.clamp(raw, max=ALPHA_MAX)
            al = torch.where(inside & (al >= ALPHA_MIN), al, torch.zeros_like(al))
            one_minus = 1.0 - al
            incl = torch.cumprod(one_minus, dim=1)
            keep = (incl >= T_MIN).detach()
            excl = torch.cat([torch.ones_like(incl[:, :1]), incl[:, :-1]], dim=1)
            w = al * excl * keep
            t_final = torch.prod(torch.where(keep, one_minus, torch.ones_like(one_minus)), dim=1, keepdim=True)
            c = w @ cs + t_final * background[None, :].to(dt)
            row.append(c.reshape(y1 - y0, x1 - x0, D))
            arow.append((1.0 - t_final).reshape(y1 - y0, x1 - x0, 1))
        rows.append(torch.cat(row, dim=1))
        alpha_rows.append(torch.cat(arow, dim=1))
    return torch.cat(rows, dim=0), torch.cat(alpha_rows, dim=0)
