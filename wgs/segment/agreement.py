"""Masks cut to what the other posed views support.

A voxel of the object's region is kept for view i when enough of the *other* views' masks hold
it (a vote: one bad mask cannot cut the others); view i's mask then keeps only the pixels whose
ray meets a kept voxel. Errors a view shares with none of the others (a table edge, a shadow, a
wall seen behind the object) lie outside the other views' cones and are cut; what is object
stays, since every view that sees it holds it. It only ever removes mask pixels.
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError
from ..scene.camera import Camera
from ..shape.hull import HullGrid, grid_centres, kept_box, pixel_lookup, silhouette


def votes_per_view(cameras: list[Camera], masks: list[torch.Tensor], points: torch.Tensor
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


def supported(cameras: list[Camera], masks: list[torch.Tensor], agreement: float = 0.85, resolution: int = 96,
              extent: float = 1.0, longest: int = 640, own: bool = True) -> list[torch.Tensor]:
    """Per view, [H, W] bool: pixels whose ray meets a voxel that at least `agreement` of the other
    views that see it hold in their masks (at least one other view must see it). Cameras in the
    normalised frame, where the object lies inside [-extent, extent]³. The grid's silhouettes are
    drawn at most `longest` pixels wide and scaled up (a voxel spans many pixels of a large photo).
    `own` False: the voxels need not be in view i's own mask (what the others alone say is object)."""
    def votes_at(points):  # the region any view could call object: the box of the vote
        inside, seen = votes_per_view(cameras, masks, points)
        return inside.sum(0), (inside, seen)

    need = max(2, math.ceil(agreement * (len(cameras) - 1)))
    try:
        lo, hi, (_, (inside, seen)) = kept_box(votes_at, need, resolution, extent)
    except InputError:  # no region that many views hold: each view's own vote over the whole extent
        lo, hi = torch.full((3,), -extent), torch.full((3,), extent)
        inside, seen = votes_at(grid_centres(lo, hi, resolution))[1]
    n_in, n_seen = inside.sum(0), seen.sum(0)
    out = []
    for v, cam in enumerate(cameras):
        others_in, others_seen = n_in - inside[v].int(), n_seen - seen[v].int()
        occ = (others_seen >= 1) & (others_in >= torch.ceil(agreement * others_seen.float()).int())
        if own:
            occ &= inside[v]
        small = silhouette(HullGrid(lo, hi, occ.reshape(resolution, resolution, resolution)), scaled(cam, longest))[0]
        out.append(torch.nn.functional.interpolate(small[None, None].float(), (cam.height, cam.width),
                                                   mode="nearest")[0, 0] > 0.5)
    return out
