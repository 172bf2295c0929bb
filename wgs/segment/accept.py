"""Automatic masks, made and judged: the masks `automatic_masks` proposes are used only where the
views agree on one object; otherwise the scene goes on without masks, and the record says why."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..fields import option
from ..scene.camera import Camera
from .agreement import hull_missed
from .automask import automatic_masks


@dataclass
class MaskParams:
    """The automatic masks' settings (`[prepare]` in the config)."""

    mask_agreement: float = option(
        0.85, "auto masks: share of the other views that must hold a voxel for it to stay object.", bounds=(0.0, 1.0)
    )
    # a view's mask votes only while the other voters hold at least this share of it (a mask of
    # something else, the wall's pattern or half the object, would cut the object from the others)
    mask_voter_support: float = option(
        0.7, "auto masks: a view votes only while the other voters hold this share of its mask.", bounds=(0.0, 1.0)
    )
    # a pixel the network missed is put back where the voters' silhouette allows object and its
    # colour is this many times likelier on the mask than on the background (0: never)
    mask_colour_ratio: float = option(
        10.0,
        "auto masks: how much likelier on the mask than on the background a missed pixel's colour must be to be put "
        "back (0: never).",
        bounds=(0.0, None),
    )
    mask_model: str | None = None  # an ONNX salient-object model to use instead of the packaged U^2-Net-p
    # when agreement cuts more than this share of the network's object area (mean over the views),
    # the views disagree on what the object is, and the scene goes on without masks
    mask_max_cut: float = option(
        0.3,
        "auto masks: when agreement cuts more than this share of the network's object area, the views disagree on "
        "the object and the scene goes on without masks (1: always keep them).",
        bounds=(0.0, 1.0),
    )
    # the training masks' strict hull may leave out at most this share of any training mask; more
    # means a mask misses part of the object, which the hull would then cut from every view
    mask_max_missed: float = option(
        0.05, "auto masks: the most of a training mask that the training masks' hull may leave out.", bounds=(0.0, 1.0)
    )


@dataclass
class JudgedMasks:
    """The proposal and the verdict: `used` is the proposal, or None where the scene goes on
    without masks (`record["auto_failed"]` says why)."""

    proposed: list[np.ndarray]  # [H, W] float32 in {0, 1}, one per view
    used: list[np.ndarray] | None
    record: dict


def judged_automatic_masks(
    images: list[np.ndarray],
    cameras: list[Camera],
    names: list[str],
    n_train: int,
    params: MaskParams,
    threads: int,
    min_fraction: float,
) -> JudgedMasks:
    """Masks for `images` (training views first, `n_train` of them) named `names`, and whether to use them.

    Refused when the network found nothing in a view, when agreement cut more than
    `mask_max_cut` of its object area, or when the training masks' strict hull leaves out more than
    `mask_max_missed` of one of them (a mask that misses part of the object would cut it from every view)."""
    made = automatic_masks(
        images,
        cameras,
        params.mask_agreement,
        params.mask_model,
        threads,
        min_fraction,
        params.mask_voter_support,
        params.mask_colour_ratio,
    )
    record = made.record
    for key in ("without_agreement", "not_voting", "network_found_nothing"):
        record[key] = [names[k] for k in record[key]]
    empty = record["network_found_nothing"]
    cut = record["cut_by_agreement"]["mean"]
    missed = hull_missed(cameras[:n_train], [torch.from_numpy(m > 0.5) for m in made.masks[:n_train]])
    record["training_hull_missed"] = [round(x, 4) for x in missed]
    worst = int(np.argmax(missed))
    failed = None
    if empty:  # the network saw no object there: the scene goes on as one without masks
        failed = f"the network found no object in {', '.join(empty)}"
    elif cut > params.mask_max_cut or min(m.mean() for m in made.masks) < min_fraction:
        # masks that disagree cost more than the hull gives
        failed = (
            f"the views disagree on the object: agreement cut {100 * cut:.0f} % of the network's object "
            f"area (over mask_max_cut {100 * params.mask_max_cut:.0f} %)"
        )
    elif missed[worst] > params.mask_max_missed:  # a mask misses part of the object: the hull would cut it
        failed = (
            f"the training masks disagree: their hull leaves out {100 * missed[worst]:.0f} % of the mask of "
            f"{names[worst]} (over mask_max_missed {100 * params.mask_max_missed:.0f} %)"
        )
    if failed is not None:
        return JudgedMasks(made.masks, None, {"source": "none", "auto_failed": failed, **record})
    return JudgedMasks(made.masks, made.masks, {"source": "auto", **record})
