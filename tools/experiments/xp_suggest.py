"""`wgs suggest` against random directions: for generated objects (make_scene kinds, seed as given),
the 5th photo `shape.next_view.suggest_view` picks and `--random` others drawn from the same
candidates, each rendered by make_scene's ray caster and added to the 4 photos; then the 5-view
strict hull's silhouette IoU and G_c's (`wgs coarse --preset fast`) PSNR and silhouette IoU at the
test views.

    python xp_suggest.py OUT_DIR --kinds vase,bottle,box,cabinet,mug,table --seed 21 [--random 3]

Prints a table; every run's workspace stays under OUT_DIR (rerunning skips what is done).
"""

import argparse
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import make_scene  # noqa: E402

from wgs.gaussians.splats import load_checkpoint  # noqa: E402
from wgs.gaussians.trainer import render_frame  # noqa: E402
from wgs.io.images import write_png  # noqa: E402
from wgs.metrics import psnr  # noqa: E402
from wgs.scene.convention import GL_TO_CV, invert_rigid  # noqa: E402
from wgs.scene.dataset import composite, load_prepared  # noqa: E402
from wgs.scene.orbit import sphere_views  # noqa: E402
from wgs.shape.hull import silhouette, visual_hull_grid  # noqa: E402
from wgs.shape.next_view import ABOVE_DEG, BELOW_DEG, CANDIDATES, loose_voxels, suggest_view  # noqa: E402
from wgs.shape.scores import silhouette_scores  # noqa: E402
from wgs.stages.shared import background_for  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def wgs(*args: str) -> None:
    subprocess.run(
        [sys.executable, "-m", "wgs", *args],
        check=True,
        stdout=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )


def with_fifth(base: Path, out: Path, obj, camera, norm) -> Path:
    """base's scene with one more training photo from `camera` (normalised world) -> out."""
    if (out / "transforms_train.json").is_file():
        return out
    shutil.copytree(base, out)
    c2w = invert_rigid(norm.w2c_from_normalised(camera.viewmat.double().numpy())) @ GL_TO_CV
    size = camera.width
    write_png(out / "train" / "r_extra.png", make_scene.render(obj, c2w, size).astype(np.float32))
    meta = json.loads((out / "transforms_train.json").read_text())
    meta["frames"].append({"file_path": "./train/r_extra", "transform_matrix": c2w.tolist()})
    (out / "transforms_train.json").write_text(json.dumps(meta, indent=2))
    return out


def scores(scene_dir: Path, ws: Path) -> dict[str, float]:
    if not (ws / "1_coarse").is_dir():
        wgs("-w", str(ws), "prepare", str(scene_dir), "--mirror", "none")
        wgs("-w", str(ws), "coarse", "--preset", "fast")
    w = Workspace(ws)
    scene = load_prepared(w.output("prepare", "prepared"), load_test_images=True)
    hull = visual_hull_grid(scene.train, 64, tolerate=0)
    splats, _ = load_checkpoint(w.output("coarse", "model"), scene.norm)
    bg = background_for(scene)
    rows = []
    for f in scene.test:
        rgb, alpha = render_frame(splats, f, torch.device("cpu"), bg)
        rows.append(
            {
                "hull_iou": silhouette_scores(silhouette(hull, f)[0], f.mask > 0.5)["iou"],
                "psnr": psnr(rgb, composite(f.image, f.mask, bg)),
                "iou": silhouette_scores(alpha[..., 0] > 0.5, f.mask > 0.5)["iou"],
            }
        )
    return {k: statistics.fmean(r[k] for r in rows) for k in rows[0]}


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--kinds", default="vase,bottle,box,cabinet,mug,table")
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--random", type=int, default=3)
    ap.add_argument("--size", type=int, default=128)
    a = ap.parse_args()
    print(
        "| object | suggested: sentence | hull IoU | G_c PSNR | G_c IoU | random (median of "
        f"{a.random}): hull IoU | G_c PSNR | G_c IoU |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for kind in a.kinds.split(","):
        base = (
            make_scene.make_scene(a.out / f"{kind}_4", seed=a.seed, size=a.size, kind=kind, sphere=True)
            if not (a.out / f"{kind}_4" / "transforms_train.json").is_file()
            else a.out / f"{kind}_4"
        )
        obj = make_scene.make_shape(kind, np.random.default_rng(a.seed))
        ws4 = a.out / f"{kind}_4_ws"
        if not (ws4 / "0_scene").is_dir():
            wgs("-w", str(ws4), "prepare", str(base), "--mirror", "none")
        scene = load_prepared(Workspace(ws4).output("prepare", "prepared"))
        record = suggest_view(*loose_voxels(visual_hull_grid(scene.train, 64, tolerate=0)), scene.photos)
        pool = [f for f, _ in sphere_views(scene.photos, CANDIDATES, BELOW_DEG, ABOVE_DEG)]
        picks = random.Random(a.seed).sample(range(len(pool)), a.random)
        best = scores(
            with_fifth(base, a.out / f"{kind}_suggested", obj, record["camera"], scene.norm),
            a.out / f"{kind}_suggested_ws",
        )
        rand = [
            scores(
                with_fifth(base, a.out / f"{kind}_random{i}", obj, pool[i], scene.norm), a.out / f"{kind}_random{i}_ws"
            )
            for i in picks
        ]
        med = {k: statistics.median(r[k] for r in rand) for k in rand[0]}
        print(
            f"| {kind} | {record['sentence']} | {best['hull_iou']:.3f} | {best['psnr']:.2f} | {best['iou']:.3f} "
            f"| {med['hull_iou']:.3f} | {med['psnr']:.2f} | {med['iou']:.3f} |",
            flush=True,
        )
