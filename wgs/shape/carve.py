"""Carving the visual hull with predictions, never against a real mask.

Two kinds of prediction carve: silhouettes at pseudo views (S), where a voxel goes when enough of
the views that see it call its pixel background with high confidence (object probability under
`empty_below` after growing the prediction by `dilate_px`), and an object probability per voxel
(V), where a voxel goes when it is under `volume_empty_below`; V carves only an object whose
leave-one-out silhouettes it does not make worse (`carve_with_volume`). At most `max_carve` of the
hull goes per call, the most certain first. Real masks are evidence the predictions cannot overrule: every
pixel of a real mask that the hull covered stays covered, by restoring the carved voxels on its ray.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from ..masking import grow
from ..scene.camera import Camera
from .hull import HullGrid, box_rays, march, pixel_lookup, silhouette
from .scores import leave_one_out, mean_scores
from .volume import occupied_probability


@dataclass
class CarveParams:
    """Thresholds of `carve`, the one place their defaults live."""

    empty_below: float = 0.3  # a pixel calls a voxel background when its object probability is under this
    dilate_px: int = 2  # predicted silhouettes are grown by this many pixels first
    min_views: int = 2  # pseudo views that must call a voxel background
    # ... and at least this fraction of the pseudo views that see it (0: min_views decides alone; a
    # voxel outside the object is outside the silhouettes of the views that see it in profile, often
    # a minority)
    min_fraction: float = 0.0
    max_carve: float = 0.5  # at most this fraction of the hull's voxels goes in one call
    volume_empty_below: float = 0.5  # a voxel goes when the volume model V's object probability is under this
    # V is left out of an object whose leave-one-out IoU (each training mask against the hull of the
    # others) falls by more than this when V carves those hulls
    volume_check_margin: float = 0.005


def sure_background(object_prob: torch.Tensor, params: CarveParams) -> torch.Tensor:
    """[H, W] bool: where the object probability [H, W], grown by `dilate_px`, stays under `empty_below`."""
    return grow(object_prob, params.dilate_px) < params.empty_below


def background_votes(
    grid: HullGrid, views: Sequence[Camera], object_prob: list[torch.Tensor], params: CarveParams
) -> tuple[torch.Tensor, torch.Tensor]:
    """For each occupied voxel (in occ.nonzero order): how many views see it [M] and how many call
    it background [M]."""
    pts = grid.centres()[grid.occ.reshape(-1)]
    seen = torch.zeros(pts.shape[0], dtype=torch.int32)
    empty = torch.zeros(pts.shape[0], dtype=torch.int32)
    for cam, prob in zip(views, object_prob, strict=True):
        inside, idx = pixel_lookup(cam, pts)
        seen += inside.int()
        empty += (inside & sure_background(prob, params).reshape(-1)[idx]).int()
    return seen, empty


def carve(
    grid: HullGrid,
    views: Sequence[Camera],
    object_prob: list[torch.Tensor],
    real: list,
    params: CarveParams | None = None,
) -> tuple[HullGrid, dict[str, int]]:
    """The hull with the voxels the predicted silhouettes call background removed.

    views / object_prob: pseudo cameras and their predicted object probability [H, W] in [0, 1];
    real: the training frames (with masks) whose covered mask pixels must stay covered.
    Returns the carved grid and counts (voxels before, carved, restored for the real masks).
    """
    params = params or CarveParams()
    seen, empty = background_votes(grid, views, object_prob, params)
    ratio = empty.float() / seen.clamp_min(1).float()
    return remove_voxels(grid, (empty >= params.min_views) & (ratio >= params.min_fraction), ratio, real, params)


def carve_volume(
    grid: HullGrid, voxel_prob: torch.Tensor, real: list, params: CarveParams | None = None
) -> tuple[HullGrid, dict[str, int]]:
    """The hull with the voxels whose object probability voxel_prob [M] (occupied voxels, occ.nonzero
    order) is under `volume_empty_below` removed; real and the counts as in `carve`."""
    params = params or CarveParams()
    return remove_voxels(grid, voxel_prob < params.volume_empty_below, 1.0 - voxel_prob, real, params)


def carve_with_volume(
    model: torch.nn.Module, frames: list, grid: HullGrid, params: CarveParams, resolution: int
) -> tuple[HullGrid, dict]:
    """V's carving of the hull (`carve_volume`), checked on the object's own evidence first: each
    training mask against the hull of the other masks (at `resolution`), carved by V and not. Where V
    makes that leave-one-out IoU worse by more than `volume_check_margin`, the hull stays as it is.
    Returns the grid and a record: the counts, the two leave-one-out IoUs (3 or more frames), used."""

    def by_volume(g: HullGrid, others: list) -> HullGrid:
        return carve_volume(g, occupied_probability(model, others, g), others, params)[0]

    check: dict = {}
    plain = mean_scores(leave_one_out(frames, resolution)) if len(frames) >= 3 else None
    carved_loo = mean_scores(leave_one_out(frames, resolution, carve=by_volume)) if plain is not None else None
    if plain is not None and carved_loo is not None:
        check = {"leave_one_out_iou": plain["iou"], "leave_one_out_iou_carved": carved_loo["iou"]}
        if check["leave_one_out_iou_carved"] < check["leave_one_out_iou"] - params.volume_check_margin:
            return grid, {**check, "used": False}
    carved, counts = carve_volume(grid, occupied_probability(model, frames, grid), frames, params)
    return carved, {**counts, **check, "used": True}


def remove_voxels(
    grid: HullGrid, drop: torch.Tensor, certainty: torch.Tensor, real: list, params: CarveParams
) -> tuple[HullGrid, dict[str, int]]:
    """Remove the occupied voxels marked in drop [M] (at most `max_carve` of them, the highest
    certainty [M] first), then restore what the real masks need."""
    flat = grid.occ.reshape(-1)
    occupied = flat.nonzero()[:, 0]
    limit = int(params.max_carve * occupied.numel())
    if int(drop.sum()) > limit:  # the most certain first
        order = torch.argsort(
            torch.where(drop, certainty, torch.full_like(certainty, -1.0)), descending=True, stable=True
        )
        drop = torch.zeros_like(drop)
        drop[order[:limit]] = True
    new = flat.clone()
    new[occupied[drop]] = False
    carved = grid.with_occupancy(new)
    restored = keep_real_coverage(grid, carved, real)
    return carved, {"voxels": int(occupied.numel()), "carved": int(drop.sum()), "restored": restored}


def keep_real_coverage(before: HullGrid, after: HullGrid, real: list) -> int:
    """Restore, in place in `after`, the carved voxels on the ray of every real mask pixel that
    `before` covered and `after` does not. Returns how many voxels came back."""
    occ_after = after.occ.reshape(-1)
    carved = before.occ.reshape(-1) & ~occ_after
    restored = 0
    for f in real:
        was = silhouette(before, f)[0] & (f.mask > 0.5)
        for _ in range(3):  # the fast path's float64 samples may name a neighbour of the reference's
            lost = (was & ~silhouette(after, f)[0]).reshape(-1).nonzero()[:, 0]
            if lost.numel() == 0:
                break
            for _, vox, _ in march(after, box_rays(after, f, lost)):
                v = vox[vox >= 0].unique()
                v = v[carved[v]]
                occ_after[v] = True
                carved[v] = False
                restored += int(v.numel())
    return restored
