"""Carving's upper bound: S replaced by the silhouettes of the hull of every true mask the scene has
(its training views and all test views, over the whole sphere), then `wgs all --carve` on a copy of
the `no-prior` workspace (`--mirror none --no-carve`) of `python -m tools.bench shape`.

    python xp_oracle_carve.py BENCH_ROOT OBJECT TAG [CONFIG.toml]

writes BENCH_ROOT/OBJECT/oracle-TAG and prints G_f's PSNR and silhouette IoU. The oracle sees the
test views' masks, so its figures bound what any S could give this carving; they are not a result.
"""

import json
import shutil
import sys
from pathlib import Path

import torch

import wgs.stages.repair.run as repair
from wgs.cli import main
from wgs.scene.dataset import load_prepared
from wgs.shape.hull import silhouette, visual_hull_grid
from wgs.workspace import Workspace

ORACLE_RESOLUTION = 160


def oracle_predictor(ws: Path, make_models):
    def predictor(scene, cfg, device):
        s = make_models(scene, cfg, device)  # keeps the stage's own checks and the strict 4-view hull
        if s is None:
            return None
        full = load_prepared(ws / "scene", load_test_images=True)
        frames = full.train + [f for f in full.test if f.mask is not None]
        every_mask = visual_hull_grid(frames, ORACLE_RESOLUTION, tolerate=0)
        print(f"oracle: the hull of {len(frames)} true masks stands in for S", flush=True)

        class Oracle(repair.ShapeModels):
            def predict(self, camera, render, alpha):
                return silhouette(every_mask, camera)[0].float()

        return Oracle(s.grid, silhouette_model=torch.nn.Identity(), volume_model=None)

    return predictor


if __name__ == "__main__":
    root, name, tag = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    config = sys.argv[4:5]
    ws = root / name / f"oracle-{tag}"
    if not ws.exists():
        shutil.copytree(root / name / "no-prior", ws)
    repair.shape_models = oracle_predictor(ws, repair.shape_models)
    try:
        main(
            [
                "-w",
                str(ws),
                *(["--config", config[0]] if config else []),
                "all",
                str(root / "scenes" / name),
                "--views",
                "4",
                "--preset",
                "fast",
                "--carve",
            ]
        )
    except SystemExit:
        pass
    res = json.loads(Workspace(ws).output("eval", "results").read_text())
    print(f"oracle {name} {tag}: G_f {res['psnr']:.2f} dB, silhouette IoU {res['silhouette_iou']:.3f}")
