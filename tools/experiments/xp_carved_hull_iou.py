"""What carving leaves of the strict hull, scored at the test views of the held-out meshes of
`python -m tools.bench shape --root BENCH_ROOT`: the strict hull, S's carved hull (from a workspace
that ran carving with S alone), V's carving at two thresholds, and V's and S's intersected, each
with the real masks' rule applied to the strict hull. No training: silhouettes of voxel grids only (about 30 s).

    python xp_carved_hull_iou.py BENCH_ROOT S_TAG [V_FOLDER]

S_TAG names the workspace under BENCH_ROOT/OBJECT/ whose repair stage carved with S alone;
V_FOLDER defaults to the shipped V.
"""

import sys
from pathlib import Path

from wgs.models.storage import load_model
from wgs.scene.dataset import load_prepared
from wgs.shape.carve import keep_real_coverage
from wgs.shape.hull import load_grid, silhouette, visual_hull_grid
from wgs.shape.volume import occupied_probability
from wgs.weights import WEIGHTS_V
from wgs.workspace import Workspace

OBJECTS = ("common-3d-test-models-cow", "common-3d-test-models-teapot", "common-3d-test-models-rocker-arm")


def mean_iou(grid, frames) -> float:
    scores = []
    for f in frames:
        a, b = silhouette(grid, f)[0], f.mask > 0.5
        scores.append(float((a & b).sum() / (a | b).sum()))
    return sum(scores) / len(scores)


if __name__ == "__main__":
    root, s_tag = Path(sys.argv[1]), sys.argv[2]
    model, _ = load_model(Path(sys.argv[3]) if len(sys.argv) > 3 else WEIGHTS_V)
    for name in OBJECTS:
        ws = Workspace(root / name / s_tag)
        scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
        strict = visual_hull_grid(scene.train, 96, tolerate=0)
        by_s = load_grid(ws.output("repair", "carved_hull"))
        prob = occupied_probability(model, scene.train, strict)
        row = {"strict hull": mean_iou(strict, scene.test), "S": mean_iou(by_s, scene.test)}
        for below in (0.3, 0.5):
            keep = strict.occ.reshape(-1).clone()
            keep[keep.clone()] = prob >= below
            by_v = strict.with_occupancy(keep)
            keep_real_coverage(strict, by_v, scene.train)
            both = strict.with_occupancy(keep & by_s.occ.reshape(-1))
            keep_real_coverage(strict, both, scene.train)
            row[f"V at {below}"], row[f"V at {below} and S"] = mean_iou(by_v, scene.test), mean_iou(both, scene.test)
        print(name, {k: round(v, 3) for k, v in row.items()}, flush=True)
