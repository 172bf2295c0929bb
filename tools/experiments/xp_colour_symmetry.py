"""Colour symmetry of an object with an accepted mirror plane: do the photos' colours at mirrored
points agree as well as at the same point seen by two photos? Points are the strict hull's first
hits (photos and their mirror images), a point counts where another photo's hull depth reaches it.

    python tools/experiments/xp_colour_symmetry.py WS   # a workspace after `wgs prepare` with the mirror used
"""

import sys

import torch

from wgs.scene.dataset import load_prepared
from wgs.scene.mirror import MirrorPlane, reflect
from wgs.shape.hull import silhouette, visual_hull_grid
from wgs.workspace import Workspace

ws = Workspace(sys.argv[1])
scene = load_prepared(ws.output("prepare", "prepared"))
if not scene.info.get("mirror", {}).get("used"):
    raise SystemExit("the scene's mirror check did not pass: no plane")
plane = MirrorPlane.from_json(scene.info["mirror"]["plane"])
photos = scene.photos
grid = visual_hull_grid(scene.train, 96, tolerate=0)
depths = [silhouette(grid, f)[1] for f in photos]
cell = float(grid.cell.max())


def points_of(i: int, stride: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """World points of photo i's object pixels (every stride-th) at the hull's depth, and their colours."""
    f = photos[i]
    v, u = torch.meshgrid(torch.arange(f.height), torch.arange(f.width), indexing="ij")
    sel = (f.mask > 0.5) & torch.isfinite(depths[i]) & (v % stride == 0) & (u % stride == 0)
    u, v = u[sel].float() + 0.5, v[sel].float() + 0.5
    ray = torch.stack([(u - f.K[0, 2]) / f.K[0, 0], (v - f.K[1, 2]) / f.K[1, 1], torch.ones_like(u)], -1)
    x_cam = ray / ray.norm(dim=-1, keepdim=True) * depths[i][sel][:, None]  # the march's depth runs along the ray
    return (x_cam - f.viewmat[:3, 3]) @ f.viewmat[:3, :3], f.image[sel]


def look_up(j: int, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Which points photo j sees (in its mask, at its hull depth within 3 cells), and its colours there."""
    f = photos[j]
    xc = points @ f.viewmat[:3, :3].T + f.viewmat[:3, 3]
    u = (f.K[0, 0] * xc[:, 0] / xc[:, 2] + f.K[0, 2]).floor().long()
    v = (f.K[1, 1] * xc[:, 1] / xc[:, 2] + f.K[1, 2]).floor().long()
    inside = (xc[:, 2] > 0) & (u >= 0) & (v >= 0) & (u < f.width) & (v < f.height)
    u, v = u.clamp(0, f.width - 1), v.clamp(0, f.height - 1)
    seen = inside & (f.mask[v, u] > 0.5) & ((xc.norm(dim=-1) - depths[j][v, u]).abs() < 3 * cell)
    return seen, f.image[v, u]


same, mirrored = [], []
for i in range(len(photos)):
    pts, colour = points_of(i)
    reflected = reflect(pts, plane.normal[None], torch.tensor([plane.offset]))[0]
    for j in range(len(photos)):
        for target, out in ((pts, same), (reflected, mirrored)):
            if target is pts and j == i:
                continue
            seen, other = look_up(j, target)
            out.append((colour[seen] - other[seen]).abs().mean(-1))
same, mirrored = torch.cat(same), torch.cat(mirrored)
print(
    f"{sys.argv[1]}: mean colour difference, same point {same.mean():.4f} (n {len(same)}), mirrored point "
    f"{mirrored.mean():.4f} (n {len(mirrored)}), ratio {mirrored.mean() / same.mean():.2f}"
)
