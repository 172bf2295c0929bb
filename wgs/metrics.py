"""Image quality metrics as the 3DGS papers compute them.

PSNR: per image, averaged over images by the caller. SSIM: 11x11 Gaussian window (sigma 1.5) with
zero padding, mean of the map (the 3DGS / GaussianObject code; kornia's reflect-padded SSIM,
used as the training loss, gives slightly different numbers). LPIPS lives in `lpips.py`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def psnr(a: torch.Tensor, b: torch.Tensor, max_val: float = 1.0) -> float:
    """PSNR in dB of two images in [0, max_val] (any matching shape). Identical images give +inf."""
    mse = float(((a.double() - b.double()) ** 2).mean())
    return math.inf if mse == 0 else 10.0 * math.log10(max_val**2 / mse)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float64) -> torch.Tensor:
    """The normalised 1D Gaussian; the 2D window is its outer product."""
    x = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> float:
    """SSIM of two images [H, W, C] in [0, 1] (zero-padded Gaussian window, mean over the map).

    Two identical images give 1. Constant images are well defined through the C1, C2 terms.
    """
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim expects two [H, W, C] images of one shape, got {tuple(a.shape)}, {tuple(b.shape)}")
    x = a.permute(2, 0, 1)[None].double()
    y = b.permute(2, 0, 1)[None].double()
    c = x.shape[1]
    g = gaussian_window(window, sigma).to(x.device)
    gx = g.reshape(1, 1, 1, -1).repeat(c, 1, 1, 1)
    gy = g.reshape(1, 1, -1, 1).repeat(c, 1, 1, 1)
    pad = window // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        # separable: with zero padding, rows then columns equals the 11x11 window exactly
        return F.conv2d(F.conv2d(t, gx, padding=(0, pad), groups=c), gy, padding=(pad, 0), groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return float((num / den).mean())
