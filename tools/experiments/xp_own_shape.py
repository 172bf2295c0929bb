"""The hull against `shape.own_shape`'s result at a prepared scene's test views: silhouette IoU,
excess and missed area (test masks), what each step chose, and seconds.

    python xp_own_shape.py WORKSPACE [WORKSPACE ...] [--resolution 64] [--no-revolution] [--no-smooth]

Each WORKSPACE holds a prepared scene (`wgs prepare`) whose test views have masks.
"""

import argparse
import statistics
from pathlib import Path

from wgs.scene.dataset import load_prepared
from wgs.shape.hull import silhouette, visual_hull_grid
from wgs.shape.own_shape import OwnShapeParams, describe, own_shape
from wgs.shape.scores import silhouette_scores
from wgs.workspace import Workspace


def test_scores(grid, frames) -> dict[str, float]:
    per = [silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5) for f in frames]
    return {k: statistics.fmean(s[k] for s in per) for k in per[0]}


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--no-revolution", action="store_true")
    ap.add_argument("--no-smooth", action="store_true")
    a = ap.parse_args()
    params = OwnShapeParams(shape_revolution=not a.no_revolution, shape_smooth=not a.no_smooth)
    print("| scene | hull IoU | own-shape IoU | hull excess | own-shape excess | own-shape missed | what | s |")
    print("|---|---|---|---|---|---|---|---|")
    for w in a.workspaces:
        scene = load_prepared(Workspace(w).output("prepare", "prepared"), load_test_images=True)
        hull = visual_hull_grid(scene.train, a.resolution, tolerate=0)
        shape, rec = own_shape(hull, scene.photos, params)
        before, after = test_scores(hull, scene.test), test_scores(shape, scene.test)
        print(
            f"| {w.name} | {before['iou']:.3f} | {after['iou']:.3f} | {before['excess']:.3f} | {after['excess']:.3f} "
            f"| {after['missed']:.3f} | {describe(rec)} | {rec['seconds']} |",
            flush=True,
        )
