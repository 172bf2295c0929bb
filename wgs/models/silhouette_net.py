"""S: the probability that each pixel at a novel pose shows the object.

Input at a pose (`shape.features.silhouette_inputs`, 6 channels): the coarse model's render (3)
and opacity (1), the visual hull's silhouette (1) and its depth relative to the hull's centre (1).
Output: object logits [B, 1, H, W]. A U-Net with `levels` downsamplings (widths c, 2c, 4c, 4c, ...):
its receptive field spans a good part of the object, which shape needs (a corner of the hull that
no view cut off is recognised by the outline around it). S runs with the image's longer side at
`work_size` pixels, the size of its training pairs (`shape.features.predict_object`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .blocks import ResBlock, pad_to_multiple, unet_pass


@dataclass
class SilhouetteNetConfig:
    in_channels: int = 6
    channels: int = 16
    levels: int = 3  # downsamplings
    work_size: int = 64  # the image's longer side, in pixels, at which S is trained and run


class SilhouetteNet(nn.Module):
    def __init__(self, config: SilhouetteNetConfig):
        super().__init__()
        self.config = config
        c, n = config.channels, config.levels
        widths = [c, 2 * c] + [4 * c] * (n - 1)
        self.inp = nn.Conv2d(config.in_channels, c, 3, padding=1)
        self.enc = nn.ModuleList(ResBlock(widths[max(i - 1, 0)], widths[i]) for i in range(n + 1))
        self.down = nn.ModuleList(nn.Conv2d(widths[i], widths[i], 3, stride=2, padding=1) for i in range(n))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.dec = nn.ModuleList(ResBlock(widths[i + 1] + widths[i], widths[i]) for i in range(n))
        self.out = nn.Conv2d(c, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [B, 6, H, W] -> object logits [B, 1, H, W]."""
        x, (h, w) = pad_to_multiple(x, 2**self.config.levels)
        y = unet_pass(self.inp(x), self.enc, self.down, self.dec, self.up)
        return self.out(y)[..., :h, :w]

    def config_dict(self) -> dict:
        return {"class": "SilhouetteNet", **asdict(self.config)}
