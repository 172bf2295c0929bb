"""Masks for posed photos that have none: saliency, agreement between views, refinement."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ..scene.camera import Camera
from .agreement import vote_grid, vote_need, vote_silhouettes, voting_views
from .colour import complete
from .refine import refine
from .saliency import SaliencyNet


@dataclass
class AutoMasks:
    masks: list[np.ndarray]  # [H, W] float32 in {0, 1}, one per view, in the order given
    record: dict  # the model, the settings, what agreement removed and where it could not, the time per photo


def automatic_masks(
    images: list[np.ndarray],
    cameras: list[Camera],
    agreement: float,
    model: str | None,
    threads: int,
    min_fraction: float,
    voter_support: float,
    colour_ratio: float,
) -> AutoMasks:
    """Object masks for `images` [H, W, 3] in [0, 1] taken by `cameras` (normalised frame).

    Order: the network's probability per photo; the views whose regions vote (`agreement.voting_views`:
    a region the other voters hold less than `voter_support` of does not); each region cut to what
    the other voters support (`agreement.supported`, skipped with fewer than 3 views); the probability,
    limited to the supported pixels, refined along the photo's edges and cleaned (`refine`); then
    what the network missed inside the voters' silhouette, put back by colour (`colour.complete`,
    `colour_ratio`; skipped with fewer than 3 views or a ratio of 0). A view
    of which the others support less than `min_fraction` of the image (the network saw something
    else there) takes what the other views alone call object: the silhouette of their vote, fatter
    than the object but consistent with the other masks (listed in the record's `without_agreement`)."""
    t0 = time.perf_counter()
    net = SaliencyNet(model, threads)
    probs = [net(img) for img in images]
    t_net = time.perf_counter() - t0
    raw = [torch.from_numpy(p > 0.5) for p in probs]
    cams = [Camera(c.K.float(), c.viewmat.float(), c.width, c.height) for c in cameras]
    voted = len(cams) >= 3
    voting, held = (
        voting_views(cams, raw, agreement, voter_support)
        if voted
        else (torch.ones(len(cams), dtype=torch.bool), [1.0] * len(cams))
    )
    support, theirs = raw, []  # theirs: with a vote only
    if voted:  # one vote: what the voters support within each view's mask, and what they alone call object
        grid = vote_grid(cams, raw, voting, vote_need(agreement, voting))
        support = vote_silhouettes(cams, grid, voting, agreement)
        theirs = vote_silhouettes(cams, grid, voting, agreement, own=False)
    masks, cut, alone, added = [], [], [], []
    for k, (img, p, r, s) in enumerate(zip(images, probs, raw, support, strict=True)):
        m = refine(img, np.where(s.numpy(), p, 0.0))
        if m.mean() < min_fraction:  # the others support nothing of it: what they alone call object
            m = theirs[k].numpy() if voted else refine(img, p)
            alone.append(k)
        elif voted and colour_ratio > 0:
            before = int(m.sum())
            m = complete(img, m, theirs[k].numpy(), colour_ratio)
            added.append((int(m.sum()) - before) / max(1, before))
        masks.append(m.astype(np.float32))
        cut.append(float((r.numpy() & ~m).sum() / max(1, r.numpy().sum())))
    seconds = time.perf_counter() - t0
    return AutoMasks(
        masks,
        {
            "model": net.record.to_json(),
            "agreement": agreement if len(cameras) >= 3 else None,
            "cut_by_agreement": {"mean": float(np.mean(cut)), "max": float(np.max(cut))},
            "without_agreement": alone,
            "added_by_colour": {
                "mean": float(np.mean(added)) if added else 0.0,
                "max": float(np.max(added)) if added else 0.0,
            },
            "network_found_nothing": [k for k, r in enumerate(raw) if r.float().mean() < min_fraction],
            "not_voting": [k for k in range(len(cams)) if not voting[k]],
            "held_by_voters": [round(h, 3) for h in held],
            "seconds_per_photo": round(seconds / max(1, len(images)), 3),
            "network_seconds_per_photo": round(t_net / max(1, len(images)), 3),
        },
    )


def mask_sheet(images: list[np.ndarray], masks: list[np.ndarray], height: int = 160, columns: int = 4) -> np.ndarray:
    """Photos with their mask's outline in green and the background dimmed, tiled: [H, W, 3] in [0, 1]."""
    tiles = []
    for img, m in zip(images, masks, strict=True):
        h, w = m.shape
        step = max(1, round(h / height))
        small, keep = img[::step, ::step, :3].copy(), m[::step, ::step] > 0.5
        small[~keep] *= 0.35
        pad = np.pad(keep, 1, mode="edge")
        rim = keep & ~(pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:])
        small[rim] = (0.0, 1.0, 0.0)
        tiles.append(small)
    th, tw = max(t.shape[0] for t in tiles), max(t.shape[1] for t in tiles)
    rows = -(-len(tiles) // columns)
    sheet = np.ones((rows * th, min(columns, len(tiles)) * tw, 3), np.float32)
    for k, t in enumerate(tiles):
        r, c = divmod(k, columns)
        sheet[r * th : r * th + t.shape[0], c * tw : c * tw + t.shape[1]] = t
    return sheet
