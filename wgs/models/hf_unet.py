"""U: the light U-Net that repairs the high-frequency Haar subbands.

Input: corrupted (LH, HL, HH) concatenated (9 channels) plus the corrupted LL as context (3);
output: a residual added to the corrupted HF subbands. Widths (c, 2c), one downsampling.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .blocks import ResBlock, pad_to_multiple


@dataclass
class HFUNetConfig:
    hf_channels: int = 9
    context_channels: int = 3
    channels: int = 16


class HFUNet(nn.Module):
    def __init__(self, config: HFUNetConfig):
        super().__init__()
        self.config = config
        c = config.channels
        self.inp = nn.Conv2d(config.hf_channels + config.context_channels, c, 3, padding=1)
        self.d1 = ResBlock(c, c)
        self.down = nn.Conv2d(c, 2 * c, 3, stride=2, padding=1)
        self.mid = ResBlock(2 * c, 2 * c)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.u1 = ResBlock(3 * c, c)
        self.out = nn.Conv2d(c, config.hf_channels, 3, padding=1)
        nn.init.zeros_(self.out.weight)  # starts as the identity repair
        nn.init.zeros_(self.out.bias)  # type: ignore[arg-type]  # built with a bias

    def forward(self, hf: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """hf [B, 9, H, W], context [B, 3, H, W] -> repaired hf [B, 9, H, W]."""
        x, (h, w) = pad_to_multiple(torch.cat([hf, context], 1), 2)
        h1 = self.d1(self.inp(x))
        m = self.mid(self.down(h1))
        u = self.u1(torch.cat([self.up(m), h1], 1))
        return hf + self.out(u)[..., :h, :w]

    def config_dict(self) -> dict:
        return {"class": "HFUNet", **asdict(self.config)}
