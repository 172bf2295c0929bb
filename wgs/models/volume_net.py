"""V: the probability that each cell of the hull's cube holds the object.

Input (`shape.volume.volume_inputs`, 4 channels over R³ cells): the strict visual hull and how deep
each cell lies inside the training masks. Output: object logits [B, 1, R, R, R]. A 3D U-Net with
`levels` downsamplings on a trunk at half the cube's resolution (a 3D convolution's backward pass
is costly on a CPU, and the excess is coarse), then a head at full resolution that sees the inputs
again. It sees the hull's whole shape, which a single view cannot: the wedges and corners that the
cones of a few views leave are recognised by their form.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .blocks import groups, unet_pass


@dataclass
class VolumeNetConfig:
    in_channels: int = 4
    channels: int = 16  # the trunk's first width; it doubles at each level
    levels: int = 2  # downsamplings below the trunk's half resolution
    resolution: int = 32  # cells per side of the cube V is trained and run on


class ResBlock3d(nn.Module):
    """GroupNorm-SiLU-conv3d x2 with a 1x1x1 skip."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(groups(cin), cin), nn.Conv3d(cin, cout, 3, padding=1)
        self.n2, self.c2 = nn.GroupNorm(groups(cout), cout), nn.Conv3d(cout, cout, 3, padding=1)
        self.skip = nn.Conv3d(cin, cout, 1) if cin != cout else nn.Identity()
        nn.init.zeros_(self.c2.weight)
        nn.init.zeros_(self.c2.bias)  # type: ignore[arg-type]  # built with a bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.c1(nn.functional.silu(self.n1(x)))
        return self.skip(x) + self.c2(nn.functional.silu(self.n2(h)))


class VolumeNet(nn.Module):
    def __init__(self, config: VolumeNetConfig):
        super().__init__()
        self.config = config
        c, n = config.channels, config.levels
        widths = [c * 2**i for i in range(n + 1)]
        self.inp = nn.Conv3d(config.in_channels, c, 3, stride=2, padding=1)
        self.enc = nn.ModuleList(ResBlock3d(widths[max(i - 1, 0)], widths[i]) for i in range(n + 1))
        self.down = nn.ModuleList(nn.Conv3d(widths[i], widths[i], 3, stride=2, padding=1) for i in range(n))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.dec = nn.ModuleList(ResBlock3d(widths[i + 1] + widths[i], widths[i]) for i in range(n))
        self.head = nn.Sequential(
            nn.Conv3d(c + config.in_channels, c // 2, 3, padding=1), nn.SiLU(), nn.Conv3d(c // 2, 1, 3, padding=1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [B, 4, R, R, R] (R a multiple of 2 ** (levels + 1)) -> object logits [B, 1, R, R, R]."""
        x = x.contiguous(memory_format=torch.channels_last_3d)  # oneDNN's fast layout for 3D convolutions
        y = unet_pass(self.inp(x), self.enc, self.down, self.dec, self.up)
        return self.head(torch.cat([self.up(y), x], 1))

    def config_dict(self) -> dict:
        return {"class": "VolumeNet", **asdict(self.config)}
