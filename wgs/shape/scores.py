"""Silhouette scores: a predicted outline against the true one, and the leave-one-out estimate of
the hull's test-view silhouettes that needs no test views."""

from __future__ import annotations

import statistics
from collections.abc import Callable

import torch

from .hull import HullGrid, silhouette, visual_hull_grid

SILHOUETTE_DOC = (
    "silhouette: rendered opacity > 0.5 against the true mask > 0.5; iou = |P & T| / |P | T|, "
    "excess = |P - T| / |T| (area the model has too much), missed = |T - P| / |T|"
)


def silhouette_scores(pred: torch.Tensor, true: torch.Tensor) -> dict[str, float]:
    """IoU, excess and missed area (fractions of the true area) of two [H, W] bool masks. An empty
    truth scores IoU 1 when the prediction is empty too, else 0."""
    pred, true = pred.bool(), true.bool()
    inter = int((pred & true).sum())
    union = int((pred | true).sum())
    area = int(true.sum())
    return {
        "iou": inter / union if union else 1.0,
        "excess": int((pred & ~true).sum()) / max(area, 1),
        "missed": int((true & ~pred).sum()) / max(area, 1),
    }


def mean_scores(per_view: dict[str, dict[str, float]]) -> dict[str, float] | None:
    """Means over views of `silhouette_scores` ({view: scores}); None without views."""
    if not per_view:
        return None
    keys = next(iter(per_view.values())).keys()
    return {k: statistics.fmean(s[k] for s in per_view.values()) for k in keys}


def leave_one_out(
    frames,
    resolution: int = 96,
    extent: float = 1.0,
    tolerate: int = 0,
    carve: Callable[[HullGrid, list], HullGrid] | None = None,
) -> dict[str, dict[str, float]]:
    """For each training frame (with a mask): the hull of the other frames' masks seen from its
    camera against its own mask. How fat a hull of N - 1 views is at a view it never saw estimates
    how fat the N-view hull is at test views, without test views. carve(hull, other frames) -> the
    hull a carving leaves, scored instead: the object's own check of that carving. {frame name: scores}."""
    out = {}
    for i, f in enumerate(frames):
        others = frames[:i] + frames[i + 1 :]
        grid = visual_hull_grid(others, resolution, extent, tolerate=tolerate)
        if carve is not None:
            grid = carve(grid, others)
        cover, _ = silhouette(grid, f)
        out[f.name] = silhouette_scores(cover, f.mask > 0.5)
    return out


# The strict hull cuts what the photos show where the hull of the other photos leaves out more than
# this share of a photo's mask, on average (lego 0.09 %, the example 0 %, generated close-ups up to
# 1.6 %, where G_f from the carved hull still beats G_f from G_c: docs/shape.md). Carving, the
# pseudo views' silhouettes and G_f's start then keep away from that hull.
HULL_CUT_LIMIT = 0.04


def hull_cut(photos, resolution: int = 96, extent: float = 1.0) -> float:
    """The mean share of each photo's mask that the strict hull of the other photos leaves out (0
    with fewer than 2 photos): how much the hull cuts of what a photo it was not built from shows."""
    if len(photos) < 2:
        return 0.0
    means = mean_scores(leave_one_out(photos, resolution, extent))
    return means["missed"] if means is not None else 0.0
