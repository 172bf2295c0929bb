"""Image quality metrics as the 3DGS papers compute them.

PSNR: per image, averaged over images by the caller. SSIM: 11x11 Gaussian window (sigma 1.5) with
zero padding, mean of the map (the 3DGS / GaussianObject code); the training loss uses the same
map reflect-padded (kornia's convention), which gives slightly different numbers. LPIPS lives in
`lpips.py`.
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


def check_ssim_inputs(x: torch.Tensor, y: torch.Tensor, padding: str) -> None:
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(
            f"ssim_map expects two [B, C, H, W] batches of one shape, got {tuple(x.shape)}, {tuple(y.shape)}"
        )
    if padding not in ("zeros", "reflect"):
        raise ValueError(f"ssim_map padding must be 'zeros' or 'reflect', got {padding!r}")


def ssim_map(
    x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, padding: str = "zeros", eps: float = 0.0
) -> torch.Tensor:
    """SSIM map of two batches [B, C, H, W] -> [B, C, H, W]; differentiable, any float dtype.

    padding "zeros": the 3DGS papers' metric; "reflect" with eps = 1e-12: kornia.metrics.ssim's
    map (the training loss). The five local moments are filtered in one separable depthwise
    Gaussian over 5C channels instead of ten convolutions: 12 ms instead of kornia's 19 ms for a
    200 x 200 forward + backward on this project's 2-core CPU.
    """
    check_ssim_inputs(x, y, padding)
    c = x.shape[1]
    g = gaussian_window(window, sigma, x.dtype).to(x.device)
    mu_x, mu_y, xx, yy, xy = blur(torch.cat([x, y, x * x, y * y, x * y], 1), g, padding).split(c, 1)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    num = (2 * mu_xy + SSIM_C1) * (2 * (xy - mu_xy) + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * ((xx - mu_xx) + (yy - mu_yy) + SSIM_C2)
    return num / (den + eps)


def blur(z: torch.Tensor, g: torch.Tensor, padding: str) -> torch.Tensor:
    """SSIM's separable Gaussian (1D window g) over each channel of [B, K, H, W], same size out:
    reflect-padded, or zero-padded ("zeros")."""
    k, window, pad = z.shape[1], g.numel(), g.numel() // 2
    if padding == "reflect":
        z, pads = F.pad(z, (pad, pad, pad, pad), mode="reflect"), ((0, 0), (0, 0))
    else:
        pads = ((0, pad), (pad, 0))
    z = F.conv2d(z, g.view(1, 1, 1, -1).expand(k, 1, 1, window), padding=pads[0], groups=k)
    return F.conv2d(z, g.view(1, 1, -1, 1).expand(k, 1, window, 1), padding=pads[1], groups=k)


def blur_adjoint(d: torch.Tensor, g: torch.Tensor, padding: str) -> torch.Tensor:
    """The adjoint of `blur` (g symmetric): what a gradient [B, K, H, W] of its output is for its input."""
    if padding != "reflect":  # a zero-padded same-size filter with a symmetric window is its own adjoint
        return blur(d, g, "zeros")
    k, window, pad = d.shape[1], g.numel(), g.numel() // 2
    full = F.conv2d(d, g.view(1, 1, -1, 1).expand(k, 1, window, 1), padding=(2 * pad, 0), groups=k)
    full = F.conv2d(full, g.view(1, 1, 1, -1).expand(k, 1, 1, window), padding=(0, 2 * pad), groups=k)
    return torch.ops.aten.reflection_pad2d_backward(full, d, [pad, pad, pad, pad])


class SSIMMapFast(torch.autograd.Function):
    """`ssim_map` against a constant y with a hand-written backward: the five local moments are
    filtered once without autograd's graph, and the gradient filters three maps instead of
    back-propagating through all five (`ssim_map` is the reference; tests compare both)."""

    @staticmethod
    def forward(ctx, x, y, window: int, sigma: float, padding: str, eps: float):
        c = x.shape[1]
        g = gaussian_window(window, sigma, x.dtype).to(x.device)
        mu_x, mu_y, xx, yy, xy = blur(torch.cat([x, y, x * x, y * y, x * y], 1), g, padding).split(c, 1)
        a1, a2 = 2 * mu_x * mu_y + SSIM_C1, 2 * (xy - mu_x * mu_y) + SSIM_C2
        b1, b2 = mu_x * mu_x + mu_y * mu_y + SSIM_C1, (xx - mu_x * mu_x) + (yy - mu_y * mu_y) + SSIM_C2
        den = b1 * b2 + eps
        out = a1 * a2 / den
        ctx.save_for_backward(x, y, mu_x, mu_y, a1, a2, b1, b2, den, out, g)
        ctx.padding = padding
        return out

    @staticmethod
    def backward(ctx, grad):
        x, y, mu_x, mu_y, a1, a2, b1, b2, den, out, g = ctx.saved_tensors
        q = grad / den
        d_a1, d_a2, d_b1, d_b2 = q * a2, q * a1, -q * out * b2, -q * out * b1
        d_mu = 2 * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2))
        back = blur_adjoint(torch.cat([d_mu, d_b2, 2 * d_a2], 1), g, ctx.padding)
        a_mu, a_xx, a_xy = back.split(x.shape[1], 1)
        return a_mu + 2 * x * a_xx + y * a_xy, None, None, None, None, None


def ssim_map_fast(
    x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, padding: str = "zeros", eps: float = 0.0
) -> torch.Tensor:
    """`ssim_map` for a loss: differentiable in x only (y is the reference)."""
    check_ssim_inputs(x, y, padding)
    return SSIMMapFast.apply(x, y.detach(), window, sigma, padding, eps)


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> float:
    """SSIM of two images [H, W, C] in [0, 1] (zero-padded Gaussian window, mean over the map).

    Two identical images give 1. Constant images are well defined through the C1, C2 terms.
    Computed in float32 unless an image is float64: 7x faster than in float64 at 200 x 200 on
    this project's 2-core CPU (2.0 against 13.9 ms), within 1.7e-6 of it on 100 of lego's renders
    and 1.1e-5 on a noisy white background (`tests/test_metrics.py`).
    """
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim expects two [H, W, C] images of one shape, got {tuple(a.shape)}, {tuple(b.shape)}")
    dtype = torch.promote_types(torch.promote_types(a.dtype, b.dtype), torch.float32)
    x, y = (t.permute(2, 0, 1)[None].to(dtype) for t in (a, b))
    return float(ssim_map(x, y, window, sigma).mean())
