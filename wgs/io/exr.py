"""Subband EXR files (OpenImageIO): one file per view, named channels `LL.R LL.G LL.B LH.R ...`.

OpenEXR stores channels sorted by name, so reads reorder by name. Half precision (the default)
cannot hold |x| > 65504: such values are clamped with a warning instead of turning into inf.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ..errors import InputError
from .images import oiio_path, write_with_oiio

HALF_MAX = 65504.0
RGB = ("R", "G", "B")
BAND_ORDER = ("LL", "LH", "HL", "HH")


def channel_names(bands: dict[str, np.ndarray]) -> list[str]:
    names: list[str] = []
    for band, arr in bands.items():
        c = arr.shape[-1]
        suffixes = RGB if c == 3 else ("Y",) if c == 1 else tuple(str(i) for i in range(c))
        names += [f"{band}.{s}" for s in suffixes]
    return names


def write_subbands(path: str | Path, bands: dict[str, np.ndarray], half: bool = True) -> None:
    """Write {name: [H, W, C] float array} into one multi-channel EXR (atomically).

    All bands must share H and W. `half=False` stores float32 (bit-exact round trip of float32).
    """
    if not bands:
        raise ValueError("no subbands to write")
    shapes = {a.shape[:2] for a in bands.values()}
    if len(shapes) != 1 or any(a.ndim != 3 for a in bands.values()):
        raise ValueError(f"subbands must all be [H, W, C] of one size, got {[a.shape for a in bands.values()]}")
    data = np.concatenate([np.asarray(a, dtype=np.float32) for a in bands.values()], axis=-1)
    if not np.isfinite(data).all():
        raise ValueError(f"{path}: refusing to write non-finite values")
    if half and np.abs(data).max(initial=0.0) > HALF_MAX:
        n = int((np.abs(data) > HALF_MAX).sum())
        warnings.warn(f"{path}: {n} values beyond the half-float range clamped to ±{HALF_MAX}", stacklevel=2)
        data = np.clip(data, -HALF_MAX, HALF_MAX)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, "half" if half else "float")
    spec.channelnames = tuple(channel_names(bands))
    spec.attribute("compression", "zip")
    write_with_oiio(Path(path), data, spec, "EXR")


def read_subbands(path: str | Path) -> dict[str, np.ndarray]:
    """Read an EXR written by `write_subbands`: {band: [H, W, C] float32} in R, G, B order."""
    path = Path(path)
    inp = oiio.ImageInput.open(oiio_path(path))
    if inp is None:
        raise InputError(f"cannot read EXR ({oiio.geterror().strip() or 'unknown error'})", path)
    try:
        names = list(inp.spec().channelnames)
        data = inp.read_image(0, 0, 0, len(names), "float")
    finally:
        inp.close()
    if data is None or not isinstance(data, np.ndarray):
        raise InputError(f"truncated or corrupt EXR ({oiio.geterror().strip()})", path)
    if data.ndim == 2:
        data = data[..., None]
    groups: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        band, _, ch = name.rpartition(".")
        groups.setdefault(band, {})[ch] = i
    out: dict[str, np.ndarray] = {}
    for band in sorted(groups, key=lambda b: (BAND_ORDER.index(b) if b in BAND_ORDER else len(BAND_ORDER), b)):
        chans = groups[band]
        if set(chans) == set(RGB):
            order = [chans[c] for c in RGB]
        elif set(chans) == {"Y"}:
            order = [chans["Y"]]
        else:
            order = [chans[k] for k in sorted(chans, key=lambda s: int(s) if s.isdigit() else s)]
        out[band] = np.ascontiguousarray(data[..., order])
    return out
