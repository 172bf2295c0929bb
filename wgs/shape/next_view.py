"""Where one more photo would help the shape most.

The hull's excess lies in corners and wedges that no photo's silhouette bounds: what a ball of half
the hull's largest inscribed radius cannot reach (`opening.opening`). A candidate camera would bound
such a voxel if the voxel falls outside the silhouette of the hull's rounded core from there: a photo
from that camera would most likely cut it. The candidate that would bound the most wins. Candidates
are spread over the sphere from 30 degrees under the lowest photo to straight above
(`scene.orbit.sphere_views`), at the photos' mean distance.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..scene.orbit import fit_orbit, sphere_views
from .hull import HullGrid, pixel_lookup, silhouette
from .opening import inscribed_distance, opening

CANDIDATES = 240  # camera directions tried
BELOW_DEG, ABOVE_DEG = 30.0, 90.0  # their band: from this far under the lowest photo to this far over the highest
CORE_FRACTION = 0.5  # the core: the opening at this fraction of the largest inscribed radius


def loose_voxels(hull: HullGrid) -> tuple[HullGrid, torch.Tensor]:
    """The hull's rounded core and the centres [N, 3] of the hull voxels outside it."""
    core = opening(hull, CORE_FRACTION * float(inscribed_distance(hull).max()))
    return core, hull.centres()[(hull.occ & ~core.occ).reshape(-1)]


def bounded_by(core: HullGrid, loose: torch.Tensor, camera) -> torch.Tensor:
    """[N] bool: the loose voxels that fall outside the core's silhouette at `camera` (in its frame)."""
    cover, _ = silhouette(core, camera)
    inside, idx = pixel_lookup(camera, loose)
    return inside & ~cover.reshape(-1)[idx]


def describe_direction(camera, photos) -> tuple[str, dict]:
    """A sentence a photographer can follow, relative to the nearest photo ("from above, 40 degrees
    to the right of photo r_2.png"), and its numbers."""
    orb = fit_orbit(photos)
    eye = camera.center.double().numpy()

    def elevation(p: np.ndarray) -> float:
        return math.degrees(math.asin(float(np.clip(p @ orb.up / np.linalg.norm(p), -1, 1))))

    def angle(a: np.ndarray, b: np.ndarray) -> float:
        return math.degrees(math.acos(float(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))

    centres = [f.center.double().numpy() for f in photos]
    near = int(np.argmin([angle(eye, c) for c in centres]))
    photo, c = photos[near], centres[near]
    right = photo.viewmat[0, :3].double().numpy()  # OpenCV x: the photographer's right
    turn = math.degrees(orb.angle_of(eye) - orb.angle_of(c))
    turn = (turn + 180.0) % 360.0 - 180.0
    side = "right" if float((eye - c) @ right) > 0 else "left"
    elev, elev_photo = elevation(eye), elevation(c)
    height = (
        "from straight above"
        if elev > 75
        else "from above"
        if elev > 45
        else "from below"
        if elev < -10
        else "from the side"
    )
    rise = elev - elev_photo
    parts = [height]
    if elev <= 75 and abs(turn) >= 10:
        parts.append(f"{abs(turn):.0f} degrees to the {side} of photo {photo.name}")
    if abs(rise) >= 10:
        parts.append(f"{abs(rise):.0f} degrees {'higher' if rise > 0 else 'lower'} than photo {photo.name}")
    if len(parts) == 1:
        parts.append(f"near photo {photo.name}")
    return ", ".join(parts), {
        "elevation_deg": round(elev, 1),
        "nearest_photo": photo.name,
        "turn_deg": round(turn, 1),
        "rise_deg": round(rise, 1),
    }


def suggest_view(core: HullGrid, loose: torch.Tensor, photos, candidates: int = CANDIDATES) -> dict:
    """The candidate camera that would bound the most loose voxels (`loose_voxels`: the hull's core
    and the centres [N, 3] outside it): a record with the camera, the share of loose voxels it
    bounds (and the median candidate's), the sentence and its numbers."""
    views = [f for f, _ in sphere_views(photos, candidates, BELOW_DEG, ABOVE_DEG)]
    counts = [int(bounded_by(core, loose, f).sum()) for f in views] if loose.shape[0] else [0] * len(views)
    best = int(np.argmax(counts))
    sentence, numbers = describe_direction(views[best], photos)
    n = max(int(loose.shape[0]), 1)
    return {
        "camera": views[best],
        "bounds": counts[best] / n,
        "median_bounds": float(np.median(counts)) / n,
        "loose_voxels": int(loose.shape[0]),
        "sentence": sentence,
        **numbers,
    }


def preview(hull: HullGrid, core: HullGrid, loose: torch.Tensor, camera) -> np.ndarray:
    """[H, W, 3] float: the hull seen from `camera`, shaded by depth, with the loose voxels
    (`loose_voxels`) that camera would bound in red."""
    cover, depth = silhouette(hull, camera)
    d = depth[cover]
    shade = torch.zeros(camera.height, camera.width)
    if d.numel():
        shade[cover] = 0.9 - 0.6 * (depth[cover] - d.min()) / (d.max() - d.min()).clamp_min(1e-6)
    img = torch.ones(camera.height, camera.width, 3)
    img[cover] = shade[cover][:, None].expand(-1, 3)
    if loose.shape[0]:
        hit = bounded_by(core, loose, camera)
        _, idx = pixel_lookup(camera, loose[hit])
        img.reshape(-1, 3)[idx] = torch.tensor([0.85, 0.1, 0.1])
    return img.numpy()
