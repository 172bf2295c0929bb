"""Masks cut to what the other posed views support.

A voxel of the object's region is kept for view i when enough of the *other* views' masks hold
it (a vote: one bad mask cannot cut the others); view i's mask then keeps only the pixels whose
ray meets a kept voxel. Errors a view shares with none of the others (a table edge, a shadow, a
wall seen behind the object) lie outside the other views' cones and are cut; what is object
stays, since every view that sees it holds it. It only ever removes mask pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import InputError
from ..scene.camera import Camera
from ..scene.dataset import Frame
from ..shape.hull import HullGrid, grid_centres, kept_box, pixel_lookup, silhouette, visual_hull_grid


def votes_per_view(
    cameras: list[Camera], masks: list[torch.Tensor], points: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """For points [N, 3]: [V, N] bool, inside view v's mask, and [V, N] bool, inside its image."""
    inside, seen = [], []
    for cam, m in zip(cameras, masks, strict=True):
        in_img, idx = pixel_lookup(cam, points)
        seen.append(in_img)
        inside.append(in_img & (m.reshape(-1)[idx] > 0.5))
    return torch.stack(inside), torch.stack(seen)


def scaled(camera: Camera, longest: int) -> Camera:
    """The camera with its image scaled down to at most `longest` pixels on its longer side."""
    s = min(1.0, longest / max(camera.width, camera.height))
    if s == 1.0:
        return camera
    K = camera.K.clone()
    K[:2] *= s
    return Camera(K, camera.viewmat, max(1, round(camera.width * s)), max(1, round(camera.height * s)))


@dataclass
class VoteGrid:
    """Every view's vote on the voxel centres of a box (normalised world): inside [V, R³] bool (in
    the view's mask), seen [V, R³] bool (in its frame)."""

    lo: torch.Tensor
    hi: torch.Tensor
    resolution: int
    inside: torch.Tensor
    seen: torch.Tensor


def vote_need(agreement: float, voters: torch.Tensor) -> int:
    """Votes a voxel needs to bound the vote's box: `agreement` of the other voters, at least 2."""
    return max(2, math.ceil(agreement * (int(voters.sum()) - 1)))


def vote_grid(
    cameras: list[Camera],
    masks: list[torch.Tensor],
    voters: torch.Tensor,
    need: int,
    resolution: int = 96,
    extent: float = 1.0,
) -> VoteGrid:
    """The views' votes on the box of the voxels that at least `need` voters hold (`hull.kept_box`),
    or on the whole [-extent, extent]³ where no voxel has that many."""

    def votes_at(points):
        inside, seen = votes_per_view(cameras, masks, points)
        return inside[voters].sum(0), (inside, seen)

    try:
        lo, hi, (_, (inside, seen)) = kept_box(votes_at, need, resolution, extent)
    except InputError:
        lo, hi = torch.full((3,), -extent), torch.full((3,), extent)
        inside, seen = votes_at(grid_centres(lo, hi, resolution))[1]
    return VoteGrid(lo, hi, resolution, inside, seen)


def vote_silhouettes(
    cameras: list[Camera], grid: VoteGrid, voters: torch.Tensor, agreement: float, longest: int = 640, own: bool = True
) -> list[torch.Tensor]:
    """Per view, [H, W] bool: the silhouette of the voxels that at least `agreement` of the other
    voters that see them hold (at least one must see them); with `own`, only those in the view's
    own mask."""
    n_in, n_seen = grid.inside[voters].sum(0), grid.seen[voters].sum(0)
    r = grid.resolution
    out = []
    for v, cam in enumerate(cameras):
        others_in = n_in - (grid.inside[v] & voters[v]).int()
        others_seen = n_seen - (grid.seen[v] & voters[v]).int()
        occ = (others_seen >= 1) & (others_in >= torch.ceil(agreement * others_seen.float()).int())
        if own:
            occ &= grid.inside[v]
        out.append(silhouette_at(HullGrid(grid.lo, grid.hi, occ.reshape(r, r, r)), cam, longest))
    return out


def supported(
    cameras: list[Camera],
    masks: list[torch.Tensor],
    agreement: float = 0.85,
    resolution: int = 96,
    extent: float = 1.0,
    longest: int = 640,
    own: bool = True,
    voters: torch.Tensor | None = None,
) -> list[torch.Tensor]:
    """Per view, [H, W] bool: pixels whose ray meets a voxel that at least `agreement` of the other
    views that see it hold in their masks (at least one other view must see it). Cameras in the
    normalised frame, where the object lies inside [-extent, extent]³. The grid's silhouettes are
    drawn at most `longest` pixels wide and scaled up (a voxel spans many pixels of a large photo).
    `own` False: the voxels need not be in view i's own mask (what the others alone say is object).
    `voters` [V] bool: the views whose masks take part in the vote (default: all)."""
    voters = torch.ones(len(cameras), dtype=torch.bool) if voters is None else voters
    grid = vote_grid(cameras, masks, voters, vote_need(agreement, voters), resolution, extent)
    return vote_silhouettes(cameras, grid, voters, agreement, longest, own)


def silhouette_at(grid: HullGrid, cam: Camera, longest: int = 640) -> torch.Tensor:
    """[H, W] bool: the grid's silhouette, drawn at most `longest` pixels wide and scaled up."""
    small = silhouette(grid, scaled(cam, longest))[0]
    return (
        torch.nn.functional.interpolate(small[None, None].float(), (cam.height, cam.width), mode="nearest")[0, 0] > 0.5
    )


def hull_missed(cameras: list[Camera], masks: list[torch.Tensor], resolution: int = 96) -> list[float]:
    """Per view, the share of its mask [H, W] bool that the strict hull of all the masks leaves out.
    Masks of one object agree (about 0); a mask that misses part of the object cuts that part from
    every view, which the training masks' hull (wgs.shape.hull, tolerating no mask) then loses."""
    frames = [
        Frame(c.K.float(), c.viewmat.float(), c.width, c.height, name=str(k), mask=m.float())
        for k, (c, m) in enumerate(zip(cameras, masks, strict=True))
    ]
    try:
        grid = visual_hull_grid(frames, resolution, tolerate=0)
    except InputError:
        return [1.0] * len(frames)
    return [
        float((m & ~silhouette_at(grid, f)).sum() / max(1, int(m.sum()))) for f, m in zip(frames, masks, strict=True)
    ]


def voting_views(
    cameras: list[Camera],
    masks: list[torch.Tensor],
    agreement: float,
    min_support: float,
    resolution: int = 96,
    extent: float = 1.0,
    longest: int = 160,
) -> tuple[torch.Tensor, list[float]]:
    """[V] bool, the views whose masks vote, and the share of each view's mask that the voters hold.

    A view whose mask shows something else (a pattern of the wall, half the object) cuts the object
    from the other views' masks wherever it sees it, since a vote tolerates few dissenters. So the
    view whose mask the other voters hold least is left out of the vote while that share is under
    `min_support`, one at a time (the worst first, as it also lowers the others' shares), and at
    least 3 views keep voting. The votes are taken once, on the box of the voxels that half the views
    hold (wider than the final vote's, so that what fewer voters keep can grow within it), and the
    shares come from silhouettes at most `longest` pixels wide."""
    voters = torch.ones(len(cameras), dtype=torch.bool)
    grid = vote_grid(cameras, masks, voters, max(2, math.ceil(0.5 * (len(cameras) - 1))), resolution, extent)
    while True:
        theirs = vote_silhouettes(cameras, grid, voters, agreement, longest, own=False)
        held = [float((m & t).sum() / max(1, int(m.sum()))) for m, t in zip(masks, theirs, strict=True)]
        worst = min((h, k) for k, h in enumerate(held) if voters[k])[1]
        if held[worst] >= min_support or int(voters.sum()) <= 3:
            return voters, held
        voters[worst] = False
