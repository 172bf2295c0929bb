"""Mask pixels the network missed, put back by their colour where the other views allow object."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .refine import clean


def colour_cells(rgb: np.ndarray, bins: int = 8) -> np.ndarray:
    """[H, W, 3] in [0, 1] -> [H, W] int: the pixel's cell among bins³ equal RGB cells."""
    q = np.clip((rgb[..., :3] * bins).astype(np.int64), 0, bins - 1)
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


def complete(
    rgb: np.ndarray, mask: np.ndarray, allowed: np.ndarray, ratio: float, bins: int = 8, margin_px: int = 3
) -> np.ndarray:
    """`mask` [H, W] bool plus the pixels of `allowed` [H, W] bool (where the other views' vote puts
    object) whose colour is at least `ratio` times likelier among the mask's pixels than among the
    sure background (outside `allowed` grown by `margin_px`), cleaned (`refine.clean`). Likelihoods
    are histograms over bins³ RGB cells, every count plus one. A part of the object that the network
    missed (a sphere before a table of another colour) comes back; background the vote allows stays
    out where its colours are the background's."""
    cells = colour_cells(rgb, bins)
    background = ~ndimage.binary_dilation(allowed, iterations=margin_px)
    if not mask.any() or not background.any():
        return mask
    n = bins**3
    p_object = np.bincount(cells[mask], minlength=n) + 1.0
    p_background = np.bincount(cells[background], minlength=n) + 1.0
    likelier = (p_object / p_object.sum()) > ratio * (p_background / p_background.sum())
    return clean(mask | (allowed & ~mask & likelier[cells]))
