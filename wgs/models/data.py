"""Repair-model data: value normalisation (one place), pair loading, random crops."""

from __future__ import annotations

from pathlib import Path

import torch

from ..errors import InputError
from ..io import read_json
from ..wavelet.haar import dwt2


def value_range(domain: str, levels: int = 1) -> tuple[float, float]:
    """LL_J of an image in [0, 1] lies in [0, 2^J] (orthonormal Haar: 2 x the 2x2 block mean per
    level); RGB in [0, 1]."""
    return (0.0, float(2**levels)) if domain == "wavelet" else (0.0, 1.0)


def to_model(x: torch.Tensor, domain: str, levels: int = 1) -> torch.Tensor:
    """Map values of the domain's range to [-1, 1] (the one place values are normalised)."""
    lo, hi = value_range(domain, levels)
    return (x - lo) * (2.0 / (hi - lo)) - 1.0


def from_model(x: torch.Tensor, domain: str, levels: int = 1) -> torch.Tensor:
    lo, hi = value_range(domain, levels)
    return (x + 1.0) * ((hi - lo) / 2.0) + lo


def hwc(a) -> torch.Tensor:
    """numpy [H, W, C] -> tensor [C, H, W]."""
    return torch.from_numpy(a).permute(2, 0, 1).contiguous()


def load_pairs(index_path: Path, domain: str, levels: int = 1) -> tuple[torch.Tensor, torch.Tensor, list[dict]]:
    """Clean and corrupted images of every pair, [P, 3, h, w] each, in model space ([-1, 1]).

    wavelet: the LL subband at `levels` (level 1 from the stored LL pairs, deeper levels from the
    stored RGB pairs); rgb: the images. `index_path`: the index `wgs mask-data` wrote, its pair
    files named relative to its folder."""
    from ..io.exr import read_subbands  # OpenImageIO only where pair files are read

    folder = index_path.parent
    index = read_json(index_path)
    pairs = index.get("pairs", [])
    if not pairs:
        raise InputError("the mask-data index lists no pairs (too few iterations after the warm-up?)", index_path)
    deep = domain == "wavelet" and levels > 1
    key, clean_band, bad_band = ("ll", "LL", "cLL") if domain == "wavelet" and not deep else ("rgb", "RGB", "cRGB")
    clean, bad = [], []
    for p in pairs:
        bands = read_subbands(folder / p[key])
        if clean_band not in bands or bad_band not in bands:
            raise InputError(f"pair file lacks {clean_band}/{bad_band}", folder / p[key])
        clean.append(hwc(bands[clean_band]))
        bad.append(hwc(bands[bad_band]))
    c, b = torch.stack(clean), torch.stack(bad)
    if deep:
        c, b = dwt2(c.double(), levels)[0].float(), dwt2(b.double(), levels)[0].float()
    return to_model(c, domain, levels), to_model(b, domain, levels), pairs


def random_crops(
    tensors: list[torch.Tensor], idx: torch.Tensor, size: int, gen: torch.Generator, flip: bool = True, align: int = 1
) -> list[torch.Tensor]:
    """The same random crop (and flips) of each tensor [P, C, H, W] at images idx -> [B, C, s, s].

    align: crop offsets are multiples of it (2 keeps Haar blocks intact).
    """
    h, w = tensors[0].shape[-2:]
    s = min(size, h, w)
    out: list[list[torch.Tensor]] = [[] for _ in tensors]
    for i in idx.tolist():
        y = int(torch.randint(0, (h - s) // align + 1, (1,), generator=gen)) * align
        x = int(torch.randint(0, (w - s) // align + 1, (1,), generator=gen)) * align
        fx, fy = (bool(torch.rand(1, generator=gen) < 0.5) for _ in range(2)) if flip else (False, False)
        for j, t in enumerate(tensors):
            c = t[i, :, y : y + s, x : x + s]
            if fx:
                c = c.flip(-1)
            if fy:
                c = c.flip(-2)
            out[j].append(c)
    return [torch.stack(o) for o in out]
