"""Mask edges that follow the photo, and no specks or small holes."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float = 1e-3) -> np.ndarray:
    """Edge-preserving smoothing of `src` [H, W] along the edges of the grey `guide` [H, W] (He, Sun
    and Tang 2013): locally src ~ a * guide + b, fitted in (2 radius + 1)² windows."""
    size = 2 * radius + 1

    def box(x: np.ndarray) -> np.ndarray:
        return ndimage.uniform_filter(x, size, mode="reflect")

    mean_i, mean_p = box(guide), box(src)
    cov_ip = box(guide * src) - mean_i * mean_p
    var_i = box(guide * guide) - mean_i * mean_i
    a = cov_ip / (var_i + eps)
    b = mean_p - a * mean_i
    return box(a) * guide + box(b)


def clean(mask: np.ndarray, min_fraction: float = 0.01) -> np.ndarray:
    """[H, W] bool without foreground pieces or background holes smaller than `min_fraction` of the
    largest foreground piece (holes that touch the border are background and stay)."""
    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    sizes = ndimage.sum_labels(mask, labels, np.arange(1, n + 1))
    keep = sizes >= min_fraction * sizes.max()
    out = keep[labels - 1] & (labels > 0)
    holes, m = ndimage.label(~out)
    if m:
        hole_sizes = ndimage.sum_labels(~out, holes, np.arange(1, m + 1))
        border = np.unique(np.concatenate([holes[0], holes[-1], holes[:, 0], holes[:, -1]]))
        small = hole_sizes < min_fraction * sizes.max()
        small[border[border > 0] - 1] = False
        out = out | (small[holes - 1] & (holes > 0))
    return out


def refine(rgb: np.ndarray, prob: np.ndarray, radius: int | None = None) -> np.ndarray:
    """A soft object probability [H, W] -> a clean binary mask [H, W] bool whose edges follow the photo."""
    h, w = prob.shape
    r = radius or max(2, round(min(h, w) / 150))
    grey = rgb[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    soft = guided_filter(grey, prob.astype(np.float64), r)
    return clean(soft > 0.5)
