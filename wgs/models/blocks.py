"""Building blocks shared by the repair networks."""

from __future__ import annotations

import math

import torch
from torch import nn


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding: t [B] -> [B, dim]."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def groups(ch: int) -> int:
    return math.gcd(8, ch)


class ResBlock(nn.Module):
    """GroupNorm-SiLU-conv x2 with an optional additive embedding and a 1x1 skip."""

    def __init__(self, cin: int, cout: int, emb: int = 0):
        super().__init__()
        self.n1 = nn.GroupNorm(groups(cin), cin)
        self.c1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.n2 = nn.GroupNorm(groups(cout), cout)
        self.c2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.emb = nn.Linear(emb, cout) if emb else None
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()
        nn.init.zeros_(self.c2.weight)
        nn.init.zeros_(self.c2.bias)  # type: ignore[arg-type]  # built with a bias

    def forward(self, x: torch.Tensor, e: torch.Tensor | None = None) -> torch.Tensor:
        h = self.c1(nn.functional.silu(self.n1(x)))
        if self.emb is not None and e is not None:
            h = h + self.emb(e)[:, :, None, None]
        h = self.c2(nn.functional.silu(self.n2(h)))
        return self.skip(x) + h


def pad_to_multiple(x: torch.Tensor, m: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """Replicate-pad [B, C, H, W] so H and W are multiples of m; returns the original size."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph or pw:
        x = nn.functional.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (h, w)


def unet_pass(
    y: torch.Tensor, enc: nn.ModuleList, down: nn.ModuleList, dec: nn.ModuleList, up: nn.Module
) -> torch.Tensor:
    """The encoder-decoder pass of S and V: enc[i] at each of len(down) + 1 levels with down[i]
    between, then back up through dec[i] with the skip of level i."""
    skips = []
    for i in range(len(enc)):
        y = enc[i](y)
        if i < len(down):
            skips.append(y)
            y = down[i](y)
    for i in reversed(range(len(dec))):
        y = dec[i](torch.cat([up(y), skips[i]], 1))
    return y
