"""The visual hull as an occupancy grid, and what it looks like from any camera.

A voxel is occupied when its centre projects inside enough training masks (all of them, or all
but `tolerate`). Its silhouette and depth at a camera come from marching each pixel's ray through
the grid at half a voxel's step: a pixel is covered when one of its samples lands in an occupied
voxel. The same marching names the voxels a pixel's ray crosses, which carving uses to keep every
real mask pixel covered.
"""

from __future__ import annotations

import hashlib
import io
import math
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from ..io import atomic_write_bytes
from ..scene.camera import Camera

EMPTY_HULL = (
    "the visual hull of the training masks is empty: the training views share no object region. "
    "Check that the masks are white on the object, that every training view sees it, and that the "
    "poses are right (camera-to-world vs world-to-camera, OpenGL vs OpenCV axes)"
)


def project_points(points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[N, 3] -> pixel coordinates [N, 2] (pixel centres at +0.5) and depth [N]."""
    p = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = p[:, 2]
    uv = (p @ K.T)[:, :2] / z.clamp_min(1e-9)[:, None]
    return uv, z


def pixel_lookup(camera: Camera, points: torch.Tensor, near: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    """Which pixel each point [N, 3] falls in: (inside [N] bool: in front and in the frame,
    flat pixel index [N] (0 where not inside))."""
    uv, z = project_points(points, camera.viewmat, camera.K)
    u, v = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
    inside = (z > near) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return inside, torch.where(inside, v * camera.width + u, torch.zeros_like(u))


# What a photo says of a point in front of it that falls outside its frame where its mask runs into
# the frame's edge (the object runs out of the photo there; where the mask stays inside the frame,
# a point outside it is background under every rule):
# - "abstain": nothing. The point needs the masks of enough other views (`votes_needed`): a photo
#   that crops the object does not cut it, and space that too few photos see is not made object.
# - "object": the border pixel's value (the photo cannot say where the object ends). Space no
#   photo sees is then object, out to the grid's extent.
# - "background": the photo cuts everything it did not show.
OFF_FRAME = ("abstain", "object", "background")
OFF_FRAME_RULE = "abstain"  # the rule every hull and vote takes (tools/experiments/xp_off_frame.py compares them)
# under "abstain" a point needs this many masks that hold it (fewer where fewer views are asked for):
# two views bound a point along a long wedge only, which a tolerant hull fills (generated close-ups:
# tolerant hull 2.9x the true hull's volume with 2, 1.8x with 3; docs/shape.md)
MIN_HOLDING_VIEWS = 3


def mask_lookup(
    camera: Camera, mask: torch.Tensor, points: torch.Tensor, near: float = 0.01, off_frame: str | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether the object `mask` [H, W] of `camera` holds each point [N, 3], and whether the photo
    abstains on it: ([N] bool, [N] bool). A point behind the camera is not held; one outside the
    frame is not held where the mask's nearest border pixel is background, and is decided by
    `off_frame` (`OFF_FRAME`) where it is object."""
    off_frame = off_frame or OFF_FRAME_RULE
    uv, z = project_points(points, camera.viewmat, camera.K)
    u, v = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])
    outside = (u < 0) | (v < 0) | (u > camera.width - 1) | (v > camera.height - 1)
    u, v = u.clamp(0, camera.width - 1).long(), v.clamp(0, camera.height - 1).long()
    border = (z > near) & (mask.reshape(-1)[v * camera.width + u] > 0.5)
    cropped = border & outside
    holds = border & ~cropped if off_frame != "object" else border
    return holds, cropped if off_frame == "abstain" else torch.zeros_like(cropped)


def votes_needed(num_views: int, tolerate: int, off_frame: str | None = None) -> int:
    """The masks that must hold a hull voxel: all but `tolerate`, and under "abstain" all but
    `tolerate` of the views that see it, at least MIN_HOLDING_VIEWS (`hull_votes` counts a voxel
    that more than `tolerate` masks leave out as -1)."""
    need = num_views - tolerate
    return min(need, MIN_HOLDING_VIEWS) if (off_frame or OFF_FRAME_RULE) == "abstain" else need


@dataclass
class HullGrid:
    """Occupancy on a regular grid of R³ voxels over the box lo..hi (normalised world).

    Attributes:
        lo, hi: [3] corners of the box.
        occ: [R, R, R] bool, indexed (x, y, z).
    """

    lo: torch.Tensor
    hi: torch.Tensor
    occ: torch.Tensor

    @property
    def resolution(self) -> int:
        return self.occ.shape[0]

    @property
    def cell(self) -> torch.Tensor:
        return (self.hi - self.lo) / self.resolution

    def centres(self) -> torch.Tensor:
        """[R³, 3] voxel centres in the order of occ.reshape(-1)."""
        return grid_centres(self.lo, self.hi, self.resolution)

    def voxel_index(self, points: torch.Tensor) -> torch.Tensor:
        """Flat index [N] of the voxel holding each point, -1 outside the box."""
        ijk = torch.floor((points - self.lo) / self.cell).long()
        inside = ((ijk >= 0) & (ijk < self.resolution)).all(-1)
        r = self.resolution
        flat = (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]
        return torch.where(inside, flat, torch.full_like(flat, -1))

    def with_occupancy(self, occ: torch.Tensor) -> HullGrid:
        return HullGrid(self.lo, self.hi, occ.reshape(self.occ.shape))


def save_grid(path, grid: HullGrid) -> None:
    """The grid as an .npz: lo, hi and the occupancy bit-packed (written atomically)."""
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        lo=grid.lo.numpy(),
        hi=grid.hi.numpy(),
        shape=np.array(grid.occ.shape),
        bits=np.packbits(grid.occ.numpy().reshape(-1)),
    )
    atomic_write_bytes(path, buf.getvalue())


def load_grid(path) -> HullGrid:
    with np.load(path) as z:
        shape = tuple(int(v) for v in z["shape"])
        occ = np.unpackbits(z["bits"])[: int(np.prod(shape))].astype(bool).reshape(shape)
        return HullGrid(torch.from_numpy(z["lo"]), torch.from_numpy(z["hi"]), torch.from_numpy(occ))


def grid_centres(lo: torch.Tensor, hi: torch.Tensor, resolution: int) -> torch.Tensor:
    axes = [
        (torch.arange(resolution, dtype=torch.float32) + 0.5) / resolution * (hi[i] - lo[i]) + lo[i] for i in range(3)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def mask_votes(frames, points: torch.Tensor, near: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    """For points [N, 3]: in how many frames' masks each falls [N] int, and the mean colour [N, 3]
    of the frames whose mask holds it (frames need image and mask)."""
    votes = torch.zeros(points.shape[0], dtype=torch.int32)
    col_sum = torch.zeros(points.shape[0], 3)
    for f in frames:
        inside, idx = pixel_lookup(f, points, near)
        in_mask = inside & (f.mask.reshape(-1)[idx] > 0.5)
        votes += in_mask.int()
        col_sum += torch.where(in_mask[:, None], f.image.reshape(-1, 3)[idx], torch.zeros(1, 3))
    return votes, col_sum / votes.clamp_min(1)[:, None].float()


def hull_votes_torch(
    frames, points: torch.Tensor, tolerate: int, near: float = 0.01, off_frame: str | None = None
) -> torch.Tensor:
    """How many frames' masks hold each point [N, 3]: [N] int, -1 where more than `tolerate` masks
    leave it out (`mask_lookup`; a frame that abstains neither holds nor leaves out). A point that
    has been left out too often is not looked up again, so each view projects only what is still
    in the running. A voxel is kept with `votes_needed` votes."""
    votes = torch.zeros(points.shape[0], dtype=torch.int32)
    missed = torch.zeros(points.shape[0], dtype=torch.int32)
    alive = torch.arange(points.shape[0])
    for f in frames:
        holds, abstains = mask_lookup(f, f.mask, points[alive], near, off_frame)
        votes[alive] += holds.int()
        missed[alive] += (~holds & ~abstains).int()
        alive = alive[missed[alive] <= tolerate]
    return torch.where(missed > tolerate, torch.full_like(votes, -1), votes)


def hull_votes(
    frames, points: torch.Tensor, tolerate: int, near: float = 0.01, off_frame: str | None = None
) -> torch.Tensor:
    """`hull_votes_torch` on the CPU numba kernel (`votes_numba`): one pass over the points, each
    projected into one view after another until too many masks have left it out."""
    from .votes_numba import hull_votes as kernel

    sizes = [f.width * f.height for f in frames]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    masks = np.concatenate([(f.mask.reshape(-1) > 0.5).to(torch.uint8).cpu().numpy() for f in frames])
    votes = kernel(
        points.detach().to("cpu", torch.float32).contiguous().numpy(),
        # C order whatever the cameras' tensors' (a transposed K stacks in Fortran order), so
        # that the kernel is compiled for one layout (`wgs.kernels`)
        np.ascontiguousarray(np.stack([f.viewmat.detach().cpu().float().numpy() for f in frames])),
        np.ascontiguousarray(np.stack([f.K.detach().cpu().float().numpy() for f in frames])),
        masks,
        offsets,
        np.array([f.width for f in frames], np.int64),
        np.array([f.height for f in frames], np.int64),
        int(tolerate),
        OFF_FRAME.index(off_frame or OFF_FRAME_RULE),
        np.float32(near),
    )
    return torch.from_numpy(votes)


def default_tolerance(num_views: int) -> int:
    """Masks a hull voxel may fall outside of: one with 3 or more views (a bad mask then cannot cut
    the object, GaussianObject's rule), else none."""
    return 1 if num_views >= 3 else 0


# The stages of one run (coarse init, repair, fine init, eval's scores, the leave-one-out checks: a
# hull per training view) ask for the same hulls again; each projects R³ voxel centres into every
# view, so a process keeps the last few by content.
HULLS_KEPT = 32
_hulls: OrderedDict[bytes, HullGrid] = OrderedDict()


def _hull_key(frames, resolution: int, extent: float, near: float, tolerate: int, off_frame: str) -> bytes:
    """Digest of everything a hull depends on: the frames' cameras and masks, the grid and the rule."""
    h = hashlib.blake2b(
        np.array([resolution, extent, near, tolerate, OFF_FRAME.index(off_frame)], np.float64).tobytes(), digest_size=20
    )
    for f in frames:
        h.update(np.array([f.width, f.height], np.int64).tobytes())
        for t in (f.viewmat, f.K, f.mask):
            h.update(t.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return h.digest()


def visual_hull_grid(
    frames,
    resolution: int = 96,
    extent: float = 1.0,
    near: float = 0.01,
    tolerate: int | None = None,
    off_frame: str | None = None,
) -> HullGrid:
    """The hull of the frames' masks over [-extent, extent]³: a 32³ pass finds its bounding box, a
    second carves that box at `resolution`. `off_frame`: what a photo says outside its frame where
    the object runs out of it (`OFF_FRAME`). Returns a copy (callers may change it); raises
    InputError when it is empty."""
    tolerate = default_tolerance(len(frames)) if tolerate is None else tolerate
    off_frame = off_frame or OFF_FRAME_RULE
    key = _hull_key(frames, resolution, extent, near, tolerate, off_frame)
    if key not in _hulls:
        _hulls[key] = _build_hull(frames, resolution, extent, near, tolerate, off_frame)
        while len(_hulls) > HULLS_KEPT:
            _hulls.popitem(last=False)
    _hulls.move_to_end(key)
    grid = _hulls[key]
    return HullGrid(grid.lo.clone(), grid.hi.clone(), grid.occ.clone())


BOX_GROWTH_STEPS = 6  # each step grows a touched side by half the box
FIRST_PASS = 32  # cells per side of the pass over the whole extent that finds the box


def kept_box(votes_at, need: int, resolution: int, extent: float = 1.0):
    """The box of what the votes keep, and the last pass's result at `resolution` cells per side.

    votes_at(points [N, 3]) -> (votes [N] int, anything): a point is kept with `need` votes.
    A 32³ pass over [-extent, extent]³ finds a first box. A part thinner than its cells (a leg, a
    handle) holds none of their centres, so that box can cut it: while the kept voxels touch a side,
    that side grows by half the box (within the extent), and the box is then made tight around them.
    Returns lo [3], hi [3] and votes_at's result at grid_centres(lo, hi, resolution); raises
    InputError when nothing is kept.
    """
    lo, hi = torch.full((3,), -extent), torch.full((3,), extent)
    pts = grid_centres(lo, hi, FIRST_PASS)
    kept = pts[votes_at(pts)[0] >= need]
    if kept.shape[0]:
        cell = (hi - lo) / FIRST_PASS
        lo, hi = torch.maximum(kept.min(0).values - cell, lo), torch.minimum(kept.max(0).values + cell, hi)
    grown = False
    for _ in range(BOX_GROWTH_STEPS):
        result = votes_at(grid_centres(lo, hi, resolution))
        occ = (result[0] >= need).reshape(resolution, resolution, resolution)
        if not occ.any():
            raise InputError(EMPTY_HULL)
        touch_lo = torch.stack([occ[0].any(), occ[:, 0].any(), occ[:, :, 0].any()]) & (lo > -extent)
        touch_hi = torch.stack([occ[-1].any(), occ[:, -1].any(), occ[:, :, -1].any()]) & (hi < extent)
        if not (touch_lo.any() or touch_hi.any()):
            break
        grown, step = True, 0.5 * (hi - lo)
        lo = torch.where(touch_lo, (lo - step).clamp_min(-extent), lo)
        hi = torch.where(touch_hi, (hi + step).clamp_max(extent), hi)
    if grown:
        cell, idx = (hi - lo) / resolution, occ.nonzero()
        lo, hi = (
            torch.maximum(lo + (idx.min(0).values - 1) * cell, torch.full_like(lo, -extent)),
            torch.minimum(lo + (idx.max(0).values + 2) * cell, torch.full_like(hi, extent)),
        )
        result = votes_at(grid_centres(lo, hi, resolution))
    return lo, hi, result


def _build_hull(frames, resolution: int, extent: float, near: float, tolerate: int, off_frame: str) -> HullGrid:
    need = votes_needed(len(frames), tolerate, off_frame)
    lo, hi, (votes,) = kept_box(
        lambda pts: (hull_votes(frames, pts, tolerate, near, off_frame),), need, resolution, extent
    )
    occ = (votes >= need).reshape(resolution, resolution, resolution)
    if not occ.any():
        raise InputError(EMPTY_HULL)
    return HullGrid(lo, hi, occ)


def surface(grid: HullGrid) -> torch.Tensor:
    """[R³] bool: occupied voxels with an empty 26-neighbour (what renders see)."""
    pad = torch.nn.functional.pad(grid.occ[None, None].float(), (1, 1, 1, 1, 1, 1))
    interior = -torch.nn.functional.max_pool3d(-pad, 3, stride=1)[0, 0] > 0.5
    return (grid.occ & ~interior).reshape(-1)


def _pixel_rays(camera: Camera, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Origin [3] and directions [P, 3] (world, scaled so that camera depth = t) of flat pixel indices."""
    u = (pixels % camera.width).float() + 0.5
    v = torch.div(pixels, camera.width, rounding_mode="floor").float() + 0.5
    d_cam = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(camera.K).T
    R = camera.viewmat[:3, :3]
    return camera.center, d_cam @ R  # R^T d for each row


@dataclass
class Rays:
    """Pixel rays that meet the grid's box: flat pixel indices [P], origin [3], directions [P, 3]
    (world, scaled so that camera depth = t), entry / exit t [P], and the step dt [P] that is half a
    voxel along each ray."""

    pixels: torch.Tensor
    origin: torch.Tensor
    dirs: torch.Tensor
    t_in: torch.Tensor
    t_out: torch.Tensor
    dt: torch.Tensor


def box_rays(grid: HullGrid, camera: Camera, pixels: torch.Tensor | None = None) -> Rays:
    """The rays of `pixels` (flat indices, default all) that meet the grid's box (slab test)."""
    if pixels is None:
        pixels = torch.arange(camera.width * camera.height)
    o, d = _pixel_rays(camera, pixels)
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (grid.lo - o) * inv, (grid.hi - o) * inv
    t_in = torch.minimum(t0, t1).max(-1).values.clamp_min(0.0)
    t_out = torch.maximum(t0, t1).min(-1).values
    hits = t_out > t_in
    d = d[hits]
    return Rays(pixels[hits], o, d, t_in[hits], t_out[hits], 0.5 * float(grid.cell.min()) / d.norm(dim=-1))


def march(grid: HullGrid, rays: Rays, chunk: int = 4096) -> Iterator[tuple[slice, torch.Tensor, torch.Tensor]]:
    """Samples t_in + (k + 0.5) dt <= t_out along the rays, in chunks: yields (the chunk's slice of
    the rays, voxel index [P, S] (-1 past the exit or outside the box), depth [P, S])."""
    for start in range(0, rays.pixels.shape[0], chunk):
        sl = slice(start, start + chunk)
        t_in, t_out, dt = rays.t_in[sl], rays.t_out[sl], rays.dt[sl]
        n = max(1, int(math.ceil(float(((t_out - t_in) / dt).max()))))
        t = t_in[:, None] + (torch.arange(n, dtype=torch.float32)[None] + 0.5) * dt[:, None]
        pts = rays.origin + t[..., None] * rays.dirs[sl, None, :]
        vox = grid.voxel_index(pts.reshape(-1, 3)).reshape(t.shape)
        yield sl, torch.where(t <= t_out[:, None], vox, torch.full_like(vox, -1)), t


def silhouette_torch(grid: HullGrid, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference of `silhouette`: every ray sampled to the box's exit."""
    rays = box_rays(grid, camera)
    occ = torch.cat([grid.occ.reshape(-1), torch.zeros(1, dtype=torch.bool)])  # index -1 -> empty
    depth = torch.full((camera.height * camera.width,), math.inf)
    for sl, vox, t in march(grid, rays):
        hit = occ[vox]
        first = t.gather(1, hit.float().argmax(-1, keepdim=True))[:, 0]
        depth[rays.pixels[sl]] = torch.where(hit.any(-1), first, torch.full_like(first, math.inf))
    depth = depth.reshape(camera.height, camera.width)
    return torch.isfinite(depth), depth


def silhouette(grid: HullGrid, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """The hull seen from `camera`: coverage [H, W] bool and depth [H, W] of the first occupied
    sample (inf where uncovered). CPU numba kernel; `silhouette_torch` is its reference."""
    from .march_numba import first_hit

    rays = box_rays(grid, camera)
    depth = torch.full((camera.height * camera.width,), math.inf)
    if rays.pixels.numel():
        hit = first_hit(
            grid.occ.reshape(-1).to(torch.uint8).numpy(),
            grid.resolution,
            grid.lo.double().numpy(),
            grid.cell.double().numpy(),
            rays.origin.double().numpy(),
            rays.dirs.double().numpy(),
            rays.t_in.double().numpy(),
            rays.t_out.double().numpy(),
            rays.dt.double().numpy(),
        )
        depth[rays.pixels] = torch.from_numpy(hit)
    depth = depth.reshape(camera.height, camera.width)
    return torch.isfinite(depth), depth
