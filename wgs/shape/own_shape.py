"""Shape from the object's own evidence: what the photos' masks allow beyond the visual hull.

The hull is the largest shape the masks allow, polygonal wherever the object is round. Two steps
shrink it toward the object, each kept only where the hull it leaves still covers the photos' own
masks (it may leave out at most `shape_max_missed` of them more than the hull does):

- **revolution**: the largest solid of revolution inside the hull, about the cameras' up direction
  or one of the hull's principal axes (`revolution.revolved`). A box's or a mug's masks show the
  corners or the handle that a solid of revolution would cut, and the step does not pass.
- **smooth**: the opening of the result at the largest radius the masks allow (`opening.opening`):
  corners and wedges that no photo bounds are rounded off at that radius.

Either way every real mask pixel keeps an occupied voxel on its ray: what the steps took from a
mask's rays (a thin handle, a leg) comes back from the hull (`carve.keep_real_coverage`).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any

import torch

from ..fields import option
from .carve import keep_real_coverage
from .hull import HullGrid, grid_centres, silhouette
from .opening import inscribed_distance, opening
from .revolution import candidate_axes, revolved, shifted
from .scores import silhouette_scores

CHECK_RESOLUTION = 64  # voxels along the hull's box where the steps are chosen and checked


@dataclass
class OwnShapeParams:
    """The steps of `own_shape`, the one place of their defaults."""

    shape_revolution: bool = option(
        True,
        "Shrink the visual hull to the largest solid of revolution inside it where the photos' masks allow it "
        "(bottles, vases, cups).",
    )
    shape_smooth: bool = option(
        True, "Round off the visual hull's corners at the largest radius the photos' masks allow."
    )
    # a step is kept where its shape leaves out at most this share of the photos' masks (mean over
    # the photos) more than the hull does, at CHECK_RESOLUTION (generated objects: solids of
    # revolution about the best axis leave out at most 0.7 % for vases and bottles, at least 2.2 %
    # for boxes, mugs and tables; docs/shape.md)
    shape_max_missed: float = option(0.015, bounds=(0.0, 1.0))


# radii the smooth step tries, as fractions of the radius of the largest ball inside the shape, the
# largest first
SMOOTH_RADII = (1.0, 0.8, 0.65, 0.5, 0.35, 0.2)


def missed_share(grid: HullGrid, photos) -> float:
    """The mean share of each photo's mask that the grid's silhouette leaves out."""
    return statistics.fmean(silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5)["missed"] for f in photos)


def resampled(grid: HullGrid, resolution: int) -> HullGrid:
    """The grid's occupancy at `resolution` cells along the same box (nearest voxel)."""
    centres = grid_centres(grid.lo, grid.hi, resolution)
    vox = grid.voxel_index(centres)
    occ = (vox >= 0) & grid.occ.reshape(-1)[vox.clamp_min(0)]
    return HullGrid(grid.lo, grid.hi, occ.reshape(resolution, resolution, resolution))


def best_revolution(check: HullGrid, photos) -> tuple[float, str, torch.Tensor, torch.Tensor]:
    """The line whose solid of revolution inside `check` leaves out the least of the photos' masks:
    (missed share, axis name, point [3], direction [3]). The axis first, through the centroid, then
    the line's place around it."""
    tried = [(missed_share(revolved(check, p, a), photos), name, p, a) for name, p, a in candidate_axes(check, photos)]
    _, name, point, axis = min(tried, key=lambda t: t[0])
    return min(
        (
            (missed_share(revolved(check, q, axis), photos), name, q, axis)
            for q in shifted(point, axis, float(check.cell.min()))
        ),
        key=lambda t: t[0],
    )


def own_shape(hull: HullGrid, photos, params: OwnShapeParams) -> tuple[HullGrid, dict]:
    """The hull shrunk by the steps the photos' masks allow, with every real mask pixel's ray kept.
    Each step is chosen and checked on the hull at `CHECK_RESOLUTION` (the same threshold at any
    resolution), then applied at the hull's own. Returns the grid and a record: the hull's missed
    share, what each step tried and kept, the voxels before and after, the voxels given back for
    the masks, seconds."""
    t0 = time.perf_counter()
    check = resampled(hull, CHECK_RESOLUTION)
    base = missed_share(check, photos)
    limit = base + params.shape_max_missed
    shape = hull
    record: dict[str, Any] = {"missed_hull": round(base, 4), "voxels": int(hull.occ.sum())}
    if params.shape_revolution:
        missed, name, point, axis = best_revolution(check, photos)
        used = missed <= limit
        record["revolution"] = {
            "axis": name,
            "point": point.tolist(),
            "direction": axis.tolist(),
            "missed": round(missed, 4),
            "used": used,
        }
        if used:
            shape, check = revolved(hull, point, axis), revolved(check, point, axis)
    if params.shape_smooth:
        largest = float(inscribed_distance(check).max())
        record["smooth"] = {"radius": None, "used": False}
        for frac in SMOOTH_RADII:
            missed = missed_share(opening(check, frac * largest), photos)
            if missed <= limit:
                shape = opening(shape, frac * largest)
                record["smooth"] = {
                    "radius": round(frac * largest, 4),
                    "fraction": frac,
                    "missed": round(missed, 4),
                    "used": True,
                }
                break
    changed = shape is not hull
    shape = shape.with_occupancy(shape.occ.clone())
    record["restored"] = keep_real_coverage(hull, shape, photos) if changed else 0
    record.update({"voxels_kept": int(shape.occ.sum()), "seconds": round(time.perf_counter() - t0, 2)})
    return shape, record


def describe(record: dict) -> str:
    """One line of what `own_shape` did and why."""
    parts = []
    rev = record.get("revolution")
    if rev is not None:
        parts.append(
            f"a solid of revolution about the {rev['axis']}"
            if rev["used"]
            else f"no solid of revolution (the best, about the {rev['axis']}, would leave out "
            f"{rev['missed']:.1%} of the photos' masks)"
        )
    sm = record.get("smooth")
    if sm is not None:
        parts.append(
            f"corners rounded at radius {sm['radius']:.3f}"
            if sm["used"]
            else "no rounding (every radius tried cuts the photos' masks)"
        )
    kept = record["voxels_kept"] / max(record["voxels"], 1)
    return f"{', '.join(parts)}: {kept:.0%} of the hull kept, {record['restored']} voxels given back for the masks"
