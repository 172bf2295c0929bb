"""Orthonormal 2D Haar DWT (analysis low-pass [1/√2, 1/√2], high-pass [-1/√2, 1/√2]).

Subbands follow PyWavelets' `dwt2(x, 'haar')`: LL = cA, LH = cH, HL = cV, HH = cD. With the 2x2 block
    a b
    c d
LL = (a+b+c+d)/2, LH = (a+b-c-d)/2, HL = (a-b+c-d)/2, HH = (a-b-c+d)/2. The transform is its own
inverse up to the block layout, so reconstruction is exact up to rounding. Odd sizes are padded by
repeating the last row/column and cropped back by `idwt2(..., size=(H, W))`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

Highs = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def _check(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.dim() != 4:
        raise ValueError(f"{name} must be a tensor of shape [B, C, H, W], got {getattr(x, 'shape', type(x))}")


def dwt2_level(x: torch.Tensor) -> tuple[torch.Tensor, Highs]:
    """One level. x: [B, C, H, W] -> LL, (LH, HL, HH), each [B, C, ceil(H/2), ceil(W/2)]."""
    _check(x, "x")
    h, w = x.shape[-2:]
    if h % 2 or w % 2:
        x = F.pad(x, (0, w % 2, 0, h % 2), mode="replicate")
    a = x[..., 0::2, 0::2]
    b = x[..., 0::2, 1::2]
    c = x[..., 1::2, 0::2]
    d = x[..., 1::2, 1::2]
    # Halving before adding keeps values near 1e38 from overflowing in float32.
    a, b, c, d = a * 0.5, b * 0.5, c * 0.5, d * 0.5
    s_ab, d_ab, s_cd, d_cd = a + b, a - b, c + d, c - d
    return s_ab + s_cd, (s_ab - s_cd, d_ab + d_cd, d_ab - d_cd)


def idwt2_level(ll: torch.Tensor, highs: Highs, size: tuple[int, int] | None = None) -> torch.Tensor:
    """Inverse of `dwt2_level`: [B, C, h, w] x4 -> [B, C, 2h, 2w], cropped to `size` if given."""
    lh, hl, hh = highs
    for t, n in ((ll, "LL"), (lh, "LH"), (hl, "HL"), (hh, "HH")):
        _check(t, n)
        if t.shape != ll.shape:
            raise ValueError(f"subband {n} has shape {tuple(t.shape)}, LL has {tuple(ll.shape)}")
    ll, lh, hl, hh = ll * 0.5, lh * 0.5, hl * 0.5, hh * 0.5
    s1, s2, d1, d2 = ll + lh, ll - lh, hl + hh, hl - hh
    a, b, c, d = s1 + d1, s1 - d1, s2 + d2, s2 - d2
    bsz, ch, h, w = ll.shape
    top = torch.stack((a, b), dim=-1).reshape(bsz, ch, h, 2 * w)
    bot = torch.stack((c, d), dim=-1).reshape(bsz, ch, h, 2 * w)
    out = torch.stack((top, bot), dim=-2).reshape(bsz, ch, 2 * h, 2 * w)
    if size is not None:
        out = out[..., : size[0], : size[1]]
    return out


def dwt2(x: torch.Tensor, levels: int = 1) -> tuple[torch.Tensor, list[Highs]]:
    """J-level Haar DWT.

    Args:
        x: [B, C, H, W], any float dtype and device.
        levels: J >= 1.
    Returns:
        LL: [B, C, H_J, W_J] with H_j = ceil(H_{j-1} / 2), and a list of J tuples (LH, HL, HH),
        finest level first (index 0 is level 1, shape [B, C, H_1, W_1]).
    """
    _check(x, "x")
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    highs: list[Highs] = []
    ll = x
    for _ in range(levels):
        ll, h = dwt2_level(ll)
        highs.append(h)
    return ll, highs


def idwt2(ll: torch.Tensor, highs: list[Highs], size: tuple[int, int] | None = None) -> torch.Tensor:
    """Inverse of `dwt2`; `size` = (H, W) of the original input crops away odd-size padding."""
    if not highs:
        raise ValueError("highs must hold at least one level")
    x = ll
    for j in range(len(highs) - 1, -1, -1):
        target = (int(highs[j - 1][0].shape[-2]), int(highs[j - 1][0].shape[-1])) if j > 0 else size
        x = idwt2_level(x, highs[j], target)
    return x


def stack_highs(highs: Highs) -> torch.Tensor:
    """(LH, HL, HH) each [B, C, h, w] -> [B, 3C, h, w] (the U-Net's input layout)."""
    return torch.cat(highs, dim=1)


def split_highs(x: torch.Tensor) -> Highs:
    """Inverse of `stack_highs`."""
    lh, hl, hh = torch.chunk(x, 3, dim=1)
    return lh, hl, hh
