"""Masks: `grow` (a mask's reach), `edge_share` (how much of a photo's edge is object), and random
region masks for the mask-data stage (WaveletGaussian's online random masking).

Each training view gets `n_regions` ellipses placed on the object. Their union is scaled so that
it hides `coverage` of the object's mask area at every iteration; with `offline=False` each region
drifts on its own sinusoid over the iterations, with `offline=True` the masks never move.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def grow(image: torch.Tensor, px: int) -> torch.Tensor:
    """[H, W] float: each pixel the largest value within px pixels (a square's reach)."""
    return torch.nn.functional.max_pool2d(image[None, None].float(), 2 * px + 1, 1, px)[0, 0]


@dataclass
class RegionMasks:
    """Region parameters for V views of size H x W (pixels).

    centers, radii, amplitude, phase: [V, n, 2]; period: [V, n] (iterations); objects: [V, H, W] bool.
    """

    centers: torch.Tensor
    radii: torch.Tensor
    amplitude: torch.Tensor
    period: torch.Tensor
    phase: torch.Tensor
    objects: torch.Tensor
    coverage: float
    offline: bool

    def hidden(self, view: int, it: int) -> torch.Tensor:
        """Binary [H, W] mask (1 = hidden, no supervision) of `view` at iteration `it`.

        Scaling every radius by s hides the pixels whose smallest normalised distance d to a region
        centre is <= s², so the s² giving `coverage` is that quantile of d over the object: exact,
        no search.
        """
        d = self._min_distance(view, self.positions(view, it))
        vals = d[self.objects[view]]
        k = max(1, math.ceil(self.coverage * vals.numel()))
        return (d <= torch.kthvalue(vals, k).values).float()

    def positions(self, view: int, it: int) -> torch.Tensor:
        if self.offline:
            return self.centers[view]
        t = 2 * math.pi * it / self.period[view]
        return self.centers[view] + self.amplitude[view] * torch.sin(t[:, None] + self.phase[view])

    def _min_distance(self, view: int, centers: torch.Tensor) -> torch.Tensor:
        """[H, W]: min over regions of ((x - cx) / rx)² + ((y - cy) / ry)² (<= 1: inside a region)."""
        h, w = self.objects.shape[1:]
        ys = torch.arange(h, dtype=torch.float32)[:, None, None] + 0.5
        xs = torch.arange(w, dtype=torch.float32)[None, :, None] + 0.5
        r = self.radii[view]
        d = ((xs - centers[:, 0]) / r[:, 0]) ** 2 + ((ys - centers[:, 1]) / r[:, 1]) ** 2
        return d.min(dim=-1).values


def edge_share(mask: torch.Tensor) -> float:
    """Share of the outermost pixels of `mask` [H, W] that are object (> 0.5): above a few per cent,
    the photo crops its object."""
    m = mask > 0.5
    edge = torch.cat([m[0], m[-1], m[1:-1, 0], m[1:-1, -1]])
    return float(edge.float().mean())


def make_region_masks(
    objects: torch.Tensor,
    n_regions: int = 10,
    coverage: float = 0.5,
    drift: float = 0.08,
    period: float = 400.0,
    offline: bool = False,
    seed: int = 0,
) -> RegionMasks:
    """Regions for object masks [V, H, W] (> 0.5 is object).

    drift: amplitude of the sinusoidal displacement, as a fraction of the object's size;
    period: mean period of the displacement in iterations (each region draws its own).
    """
    if not 0 < coverage < 1:
        raise ValueError(f"coverage must be in (0, 1), got {coverage}")
    if n_regions < 1:
        raise ValueError(f"n_regions must be >= 1, got {n_regions}")
    g = torch.Generator().manual_seed(seed)
    obj = objects > 0.5
    V = obj.shape[0]
    centers = torch.zeros(V, n_regions, 2)
    radii = torch.zeros(V, n_regions, 2)
    for v in range(V):
        ys, xs = torch.nonzero(obj[v], as_tuple=True)
        if len(ys) == 0:
            raise ValueError(f"view {v} has an empty object mask")
        pick = torch.randint(len(ys), (n_regions,), generator=g)
        centers[v, :, 0] = xs[pick].float() + 0.5
        centers[v, :, 1] = ys[pick].float() + 0.5
        size = math.sqrt(len(ys) / (n_regions * math.pi))
        radii[v] = size * torch.exp(torch.randn(n_regions, 2, generator=g) * 0.3)
    obj_size = obj.flatten(1).sum(1).float().sqrt()[:, None, None]
    amplitude = drift * obj_size * (0.5 + torch.rand(V, n_regions, 2, generator=g))
    periods = period * (0.5 + torch.rand(V, n_regions, generator=g))
    phase = 2 * math.pi * torch.rand(V, n_regions, 2, generator=g)
    return RegionMasks(centers, radii, amplitude, periods, phase, obj, coverage, offline)
