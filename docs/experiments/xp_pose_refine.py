"""Training cameras corrected while a model trains (`gaussians.pose_refine`): does it bring the
cameras that structure-from-motion gave 4 photos closer to the truth?

On the workspaces of `xp_unposed_run.py` (its `ws_unposed`, whose training cameras wgs posed, and
`posed/transforms_train.json`, the truth): one coarse model trains from the visual hull with the
corrections, and the median rotation and centre errors after a similarity alignment are given
before and after.

    python docs/experiments/xp_pose_refine.py --out DIR [--lr 1e-3 3e-4] [--iterations 1500]
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from wgs.config import CoarseConfig
from wgs.gaussians.pose_refine import CameraCorrections
from wgs.gaussians.trainer import train_gaussians
from wgs.scene.convention import c2w_opengl_to_w2c_opencv
from wgs.scene.dataset import load_prepared
from wgs.scene.pose_error import pose_errors
from wgs.stages.shared import initial_splats
from wgs.workspace import Workspace


def truth(posed: Path) -> dict[str, np.ndarray]:
    meta = json.loads((posed / "transforms_train.json").read_text())
    return {
        Path(f["file_path"]).name: c2w_opengl_to_w2c_opencv(np.array(f["transform_matrix"])) for f in meta["frames"]
    }


def medians(est: dict[str, np.ndarray], true: dict[str, np.ndarray]) -> tuple[float, float]:
    names = sorted(n for n in est if Path(n).stem in true)  # the photos (not their mirror views)
    err = pose_errors(np.stack([est[n] for n in names]), np.stack([true[Path(n).stem] for n in names]))
    return float(np.median(err["rotation_deg"])), float(np.median(err["center"]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True, help="xp_unposed_run.py's --out")
    ap.add_argument("--lr", type=float, nargs="+", default=[1e-3, 3e-4])
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--half-size", type=float, default=1.0, help="the share of iterations at half size")
    args = ap.parse_args()
    print("| scene | camera lr | rotation error (deg) before -> after | centre error (% extent) before -> after | s |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for case in sorted(p for p in args.out.iterdir() if (p / "ws_unposed").is_dir()):
        scene = load_prepared(Workspace(case / "ws_unposed").output("scene", "prepared"))
        true = truth(case / "posed")
        before = medians({f.name: f.viewmat.double().numpy() for f in scene.train}, true)
        cfg = dataclasses.replace(CoarseConfig(), iterations=args.iterations, half_size_until=args.half_size)
        for lr in args.lr:
            torch.manual_seed(0)
            cams = CameraCorrections(len(scene.train), lr, torch.device("cpu"))
            t0 = time.perf_counter()
            train_gaussians(
                initial_splats(scene, cfg, 0),
                scene.train,
                cfg,
                torch.device("cpu"),
                extent=1.0,
                cameras=cams,
                has_masks=scene.has_masks,
                desc=f"{case.name} lr {lr:g}",
            )
            seconds = time.perf_counter() - t0
            moved = cams.viewmats([f.viewmat for f in scene.train])
            after = medians({f.name: v.double().numpy() for f, v in zip(scene.train, moved, strict=True)}, true)
            print(
                f"| {case.name} | {lr:g} | {before[0]:.2f} -> {after[0]:.2f} | "
                f"{100 * before[1]:.1f} -> {100 * after[1]:.1f} | {seconds:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
