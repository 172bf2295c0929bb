"""The object's mirror plane, found from its training masks.

Many objects are mirror-symmetric (animals, faces, vehicles, tools, vessels). For such an object each
training photo has a mirror image (`scene.mirror.mirror_frame`): the reflected camera sees the
flipped photo, and the hull of the real and the mirrored masks is the hull intersected with its own
reflection (`mirror_carve`). A mirror doubles the views, and the mirrored ones look from where no
camera stood.

The plane is chosen on the object's own evidence, by leave-one-out silhouettes: for each training
mask, the hull of the other masks, intersected with its reflection, is seen from that mask's camera
and compared with the mask. The plane that predicts the left-out masks best wins, and it is used
only when it raises their mean IoU by `min_gain` over the hulls alone, and when the hull of the
photos and their mirror images still covers the photos' masks (`max_missed`): an object that is
not symmetric, or a plane that would cut what a photo saw, does not pass.
"""

from __future__ import annotations

import math
import time

import torch

from ..scene.mirror import MirrorPlane, mirror_frame, reflect
from .hull import HullGrid, box_rays, march, silhouette, visual_hull_grid
from .scores import silhouette_scores

SEARCH = (48, 3)  # (leave-one-out hull resolution, pixel stride) of the search over all directions
REFINE = (64, 1)  # ... and of the refinement around the best plane
OFFSETS = 7  # plane offsets tried per direction, over +-OFFSET_SPAN of the hull box around its centroid
OFFSET_SPAN = 0.15
# refinement rounds: (tilt step in degrees, offset step over the box's size); each tries a 7 x 7 x 7
# grid of tilts about two axes and offsets around the best plane so far
REFINE_STEPS = ((2.0, 0.01), (0.7, 0.004))
REFINE_REACH = 3


def mirrored_occupancy(grid: HullGrid, normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """[B, R³] bool: the grid's occupied voxels whose centre's mirror image lies in an occupied voxel,
    for each of B planes."""
    occ = grid.occ.reshape(-1)
    idx = occ.nonzero()[:, 0]
    mirrored = reflect(grid.centres()[idx], normals, offsets)
    vox = grid.voxel_index(mirrored.reshape(-1, 3)).reshape(mirrored.shape[:2])
    keep = torch.zeros(normals.shape[0], occ.numel(), dtype=torch.bool)
    keep[:, idx] = (vox >= 0) & occ[vox.clamp_min(0)]
    return keep


def mirror_carve(grid: HullGrid, plane: MirrorPlane) -> HullGrid:
    """The grid intersected with its reflection across the plane."""
    occ = mirrored_occupancy(grid, plane.normal[None], torch.tensor([plane.offset]))[0]
    return grid.with_occupancy(occ)


class RayVoxels:
    """The occupied voxels on each pixel ray of a camera (every stride-th pixel), so that the
    silhouette IoU of any subset of the grid's occupancy is one gather instead of a ray march."""

    def __init__(self, grid: HullGrid, camera, stride: int = 1):
        self.grid = grid
        rows = torch.arange(0, camera.height, stride)
        cols = torch.arange(0, camera.width, stride)
        pixels = (rows[:, None] * camera.width + cols[None]).reshape(-1)
        inside = camera.mask.reshape(-1)[pixels] > 0.5
        self.mask_total = int(inside.sum())
        occ = torch.cat([grid.occ.reshape(-1), torch.zeros(1, dtype=torch.bool)])  # -1 -> empty
        rays = box_rays(grid, camera, pixels)
        voxels, on_mask = [], []
        for sl, vox, _ in march(grid, rays):
            vox = torch.where(occ[vox], vox, torch.full_like(vox, -1))
            hit = (vox >= 0).any(-1)
            voxels.append(vox[hit].sort(-1, descending=True).values)  # occupied first
            on_mask.append(inside[torch.searchsorted(pixels, rays.pixels[sl][hit])])
        width = max((v.shape[1] for v in voxels), default=1)
        vox = torch.cat([torch.nn.functional.pad(v, (0, width - v.shape[1]), value=-1) for v in voxels])
        self.voxels = vox[:, : max(int((vox >= 0).sum(-1).max()) if vox.numel() else 1, 1)].contiguous()
        self.on_mask = torch.cat(on_mask)

    def iou(self, occupancy: torch.Tensor) -> torch.Tensor:
        """occupancy [B, R³] bool (subsets of the grid's) -> silhouette IoU with the mask [B]."""
        occ = torch.cat([occupancy, torch.zeros(occupancy.shape[0], 1, dtype=torch.bool)], 1)
        covered = occ[:, self.voxels].any(-1)  # [B, P]
        inter = (covered & self.on_mask).sum(-1)
        return inter / (self.mask_total + covered.sum(-1) - inter).clamp_min(1)

    def mirrored_iou(self, normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """`iou(mirrored_occupancy(self.grid, normals, offsets))` [B] on the CPU fast path."""
        from .mirror_numba import mirror_ious

        g = self.grid
        return torch.from_numpy(
            mirror_ious(
                g.occ.reshape(-1).to(torch.uint8).numpy(),
                g.resolution,
                g.lo.double().numpy(),
                g.cell.double().numpy(),
                g.centres().double().numpy(),
                normals.double().numpy(),
                offsets.double().numpy(),
                self.voxels.numpy(),
                self.on_mask.numpy(),
                self.mask_total,
            )
        ).float()


def hemisphere_directions(n: int) -> torch.Tensor:
    """n unit vectors spread evenly over the upper hemisphere (a plane's normal and its negative
    name the same plane) [n, 3]."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = i / n
    phi = math.pi * (1 + math.sqrt(5.0)) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1).float()


def leave_one_out_views(frames, resolution: int, stride: int) -> list[RayVoxels]:
    """For each frame, the hull of the other frames' masks and its rays at that frame's camera."""
    return [
        RayVoxels(visual_hull_grid(frames[:i] + frames[i + 1 :], resolution, tolerate=0), f, stride)
        for i, f in enumerate(frames)
    ]


def mirrored_loo_iou(views: list[RayVoxels], normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Mean leave-one-out IoU [B] of the hulls intersected with their reflections across B planes."""
    return torch.stack([rays.mirrored_iou(normals, offsets) for rays in views]).mean(0)


def tilted(
    normal: torch.Tensor, offset: float, tilt_deg: float, offset_step: float, reach: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Planes around (normal, offset): tilts of k * tilt_deg about two axes across the normal and
    offsets of k * offset_step, k in -reach..reach: normals [(2 reach + 1)³, 3], offsets [...]."""
    axis = torch.zeros(3)
    axis[int(normal.abs().argmin())] = 1.0
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normal, axis), dim=0)
    t2 = torch.linalg.cross(normal, t1)
    k = torch.arange(-reach, reach + 1, dtype=torch.float32)
    a, b, c = torch.meshgrid(k, k, k, indexing="ij")
    tan = math.tan(math.radians(tilt_deg))
    normals = normal + tan * (a.reshape(-1, 1) * t1 + b.reshape(-1, 1) * t2)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    return normals, offset + offset_step * c.reshape(-1)


def find_mirror(frames, directions: int) -> tuple[MirrorPlane, float, float]:
    """The plane whose mirror best predicts each training mask from the others' hull: (plane, mean
    leave-one-out IoU of the hulls alone, of the hulls intersected with their reflections), both
    measured at the refinement's resolution."""
    coarse = leave_one_out_views(frames, *SEARCH)
    whole = visual_hull_grid(frames, SEARCH[0], tolerate=0)
    centroid = whole.centres()[whole.occ.reshape(-1)].mean(0)
    size = float((whole.hi - whole.lo).max())
    dirs = hemisphere_directions(directions)
    normals = dirs.repeat_interleave(OFFSETS, 0)
    offsets = normals @ centroid + torch.linspace(-OFFSET_SPAN, OFFSET_SPAN, OFFSETS).repeat(directions) * size
    best = int(mirrored_loo_iou(coarse, normals, offsets).argmax())
    normal, offset = normals[best], float(offsets[best])
    fine = leave_one_out_views(frames, *REFINE)
    top = float(mirrored_loo_iou(fine, normal[None], torch.tensor([offset]))[0])
    for tilt, step in REFINE_STEPS:
        normals, offsets = tilted(normal, offset, tilt, step * size, REFINE_REACH)
        scores = mirrored_loo_iou(fine, normals, offsets)
        if float(scores.max()) > top:
            k = int(scores.argmax())
            normal, offset, top = normals[k], float(offsets[k]), float(scores[k])
    before = float(torch.stack([rays.iou(rays.grid.occ.reshape(1, -1))[0] for rays in fine]).mean())
    return MirrorPlane(normal, offset), before, top


def mirror_check(frames, min_gain: float, max_missed: float, directions: int) -> dict:
    """The object's mirror plane (`find_mirror`) and whether it passes: it must raise the mean
    leave-one-out IoU by min_gain, and the hull of the photos and their mirror images may miss at
    most max_missed of the photos' masks (mean over the photos; a plane the object only roughly
    follows cuts it). A record: plane, both IoUs, the missed share, used, seconds."""
    t0 = time.perf_counter()
    plane, before, after = find_mirror(frames, directions)
    both = visual_hull_grid(frames + [mirror_frame(f, plane) for f in frames], REFINE[0], tolerate=0)
    missed = sum(silhouette_scores(silhouette(both, f)[0], f.mask > 0.5)["missed"] for f in frames) / len(frames)
    return {
        "plane": plane.to_json(),
        "leave_one_out_iou": round(before, 4),
        "leave_one_out_iou_mirrored": round(after, 4),
        "missed": round(missed, 4),
        "used": after >= before + min_gain and missed <= max_missed,
        "seconds": round(time.perf_counter() - t0, 2),
    }
