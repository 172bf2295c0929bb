"""D: the conditional repair denoiser for the LL subband (or RGB, for the ablation).

A compact convolutional U-Net without attention, sized for CPU training: input = noisy clean
image (C) concatenated with the corrupted image as control signal (C). It predicts the clean
image as the corrupted one plus a residual (sample prediction): zero-initialised, it starts as
the identity repair, so a short per-object training can only move it towards the references.
Widths (c, 2c, 2c), two downsamplings, one ResBlock per level with the timestep embedding.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .blocks import ResBlock, groups, pad_to_multiple, timestep_embedding


@dataclass
class LLDenoiserConfig:
    in_channels: int = 3
    channels: int = 32
    emb_dim: int = 64


class LLDenoiser(nn.Module):
    def __init__(self, config: LLDenoiserConfig):
        super().__init__()
        self.config = config
        c, e, k = config.channels, config.emb_dim, config.in_channels
        self.emb = nn.Sequential(nn.Linear(e, e), nn.SiLU(), nn.Linear(e, e))
        self.inp = nn.Conv2d(2 * k, c, 3, padding=1)
        self.d1 = ResBlock(c, c, e)
        self.down1 = nn.Conv2d(c, 2 * c, 3, stride=2, padding=1)
        self.d2 = ResBlock(2 * c, 2 * c, e)
        self.down2 = nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1)
        self.mid = ResBlock(2 * c, 2 * c, e)
        self.up2 = nn.Upsample(scale_factor=2, mode="nearest")
        self.u2 = ResBlock(4 * c, 2 * c, e)
        self.up1 = nn.Upsample(scale_factor=2, mode="nearest")
        self.u1 = ResBlock(3 * c, c, e)
        self.out = nn.Sequential(nn.GroupNorm(groups(c), c), nn.SiLU(), nn.Conv2d(c, k, 3, padding=1))
        last = self.out[-1]
        assert isinstance(last, nn.Conv2d) and last.bias is not None
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x_t, cond: [B, C, H, W] (any H, W); t: [B] timesteps -> predicted clean image [B, C, H, W]."""
        if x_t.shape != cond.shape:
            raise ValueError(f"x_t {tuple(x_t.shape)} and cond {tuple(cond.shape)} must match")
        x, (h, w) = pad_to_multiple(torch.cat([x_t, cond], 1), 4)
        e = self.emb(timestep_embedding(t, self.config.emb_dim))
        h1 = self.d1(self.inp(x), e)
        h2 = self.d2(self.down1(h1), e)
        m = self.mid(self.down2(h2), e)
        u2 = self.u2(torch.cat([self.up2(m), h2], 1), e)
        u1 = self.u1(torch.cat([self.up1(u2), h1], 1), e)
        return cond + self.out(u1)[..., :h, :w]

    prediction = "sample"

    def config_dict(self) -> dict:
        return {"class": "LLDenoiser", "prediction": self.prediction, **asdict(self.config)}
