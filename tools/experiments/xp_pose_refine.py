"""Training cameras corrected while a model trains (`gaussians.pose_refine`): does it bring the
cameras that structure-from-motion gave 4 photos closer to the truth, and does a whole run on the
corrected cameras score better?

On the workspaces of `xp_unposed_run.py` (its `ws_unposed`, whose training cameras wgs posed, and
`posed/transforms_train.json`, the truth): one coarse model trains from the visual hull with the
corrections. Given before and after: the median rotation and centre errors after a similarity
alignment, and what the scene itself shows, the share of each photo's mask that the hull of the
other photos leaves out (the check `wgs prepare` makes of posed photos). With `--run`, the
photos with the corrected cameras (last `--lr`) become a scene of their own, `wgs all` trains on
it, and it is scored as `xp_unposed_run.py` scores its runs.

    python tools/experiments/xp_pose_refine.py --out DIR [--lr 1e-3 3e-4] [--half-size 0.3] [--run]

`--lr 0 --run` is the control: the same scene path with the cameras as posed.
"""

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from xp_unposed_run import aligned_tests, generated_scene, lego_scene, run_all, score  # noqa: E402

from wgs.gaussians.pose_refine import CameraCorrections  # noqa: E402
from wgs.gaussians.trainer import train_gaussians  # noqa: E402
from wgs.scene.convention import c2w_opengl_to_w2c_opencv  # noqa: E402
from wgs.scene.dataset import load_prepared  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402
from wgs.shape.scores import leave_one_out, mean_scores  # noqa: E402
from wgs.stages.coarse.settings import CoarseConfig  # noqa: E402
from wgs.stages.eval.scoring import spread  # noqa: E402
from wgs.stages.shared import initial_splats  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def truth(posed: Path) -> dict[str, np.ndarray]:
    meta = json.loads((posed / "transforms_train.json").read_text())
    return {
        Path(f["file_path"]).name: c2w_opengl_to_w2c_opencv(np.array(f["transform_matrix"])) for f in meta["frames"]
    }


def medians(est: dict[str, np.ndarray], true: dict[str, np.ndarray]) -> tuple[float, float]:
    names = sorted(n for n in est if Path(n).stem in true)  # the photos (not their mirror views)
    err = pose_errors(np.stack([est[n] for n in names]), np.stack([true[Path(n).stem] for n in names]))
    return float(np.median(err["rotation_deg"])), float(np.median(err["center"]))


def hull_missed(photos, viewmats) -> float:
    moved = [dataclasses.replace(f, viewmat=v) for f, v in zip(photos, viewmats, strict=True)]
    return mean_scores(leave_one_out(moved, 96))["missed"]


def write_scene(case: Path, photos, viewmats, out: Path) -> None:
    """The photos (RGBA, from `posed/train`) with the corrected cameras, as a NeRF-Synthetic scene."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    (out / "train").mkdir(parents=True, exist_ok=True)
    rows = []
    for f, v in zip(photos, viewmats, strict=True):
        stem = Path(f.name).stem
        shutil.copyfile(case / "posed" / "train" / f"{stem}.png", out / "train" / f"{stem}.png")
        rows.append(
            {"file_path": f"./train/{stem}", "transform_matrix": (np.linalg.inv(v.double().numpy()) @ flip).tolist()}
        )
    K = photos[0].K
    meta = {"camera_angle_x": float(2 * np.arctan(photos[0].width / 2 / float(K[0, 0]))), "frames": rows}
    for split in ("train", "test"):  # no test views of its own: the experiment scores at the true ones
        (out / f"transforms_{split}.json").write_text(json.dumps(meta))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True, help="xp_unposed_run.py's --out")
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    ap.add_argument("--lr", type=float, nargs="+", default=[1e-3, 3e-4])
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--half-size", type=float, default=1.0, help="the share of iterations at half size")
    ap.add_argument("--run", action="store_true", help="wgs all on the corrected cameras (last --lr), scored")
    args = ap.parse_args()
    rows, runs = [], []
    for case in sorted(p for p in args.out.iterdir() if (p / "ws_unposed").is_dir()):
        scene = load_prepared(Workspace(case / "ws_unposed").output("prepare", "prepared"))
        true = truth(case / "posed")
        photos = [f for f in scene.train if Path(f.name).stem in true]
        before = medians({f.name: f.viewmat.double().numpy() for f in photos}, true)
        missed_before = hull_missed(photos, [f.viewmat for f in photos])
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
            moved = dict(
                zip((f.name for f in scene.train), cams.viewmats([f.viewmat for f in scene.train]), strict=True)
            )
            corrected = [moved[f.name] for f in photos]
            after = medians({f.name: v.double().numpy() for f, v in zip(photos, corrected, strict=True)}, true)
            rows.append(
                f"| {case.name} | {lr:g} | {before[0]:.2f} -> {after[0]:.2f} | {100 * before[1]:.1f} -> "
                f"{100 * after[1]:.1f} | {100 * missed_before:.2f} -> {100 * hull_missed(photos, corrected):.2f} | "
                f"{seconds:.0f} |"
            )
            print(rows[-1], flush=True)
        if args.run:
            label, step = case.name.rsplit("_", 1)
            make = generated_scene if label == "generated" else (lambda s, o: lego_scene(args.lego, s, o))
            data = make(float(step), case)
            tag = f"lr{args.lr[-1]:g}"  # lr 0: the cameras as posed, through the same path (the control)
            write_scene(case, photos, corrected, case / f"corrected_{tag}")
            ws = case / f"ws_corrected_{tag}"
            wall = run_all(case / f"corrected_{tag}", ws, ["--downscale", "1" if label == "generated" else "2"])
            frames, pose = aligned_tests(ws, data["truth"], data["tests"])
            g_c, g_f = score(ws, frames, pose["norm"], "coarse"), score(ws, frames, pose["norm"], "fine")
            loc = score(ws, spread(frames, 40), pose["norm"], "fine", 60)
            runs.append(
                f"| {case.name}, camera lr {args.lr[-1]:g} | {pose['rotation_deg']:.2f} / {100 * pose['centre']:.1f} | "
                f"{g_c['psnr']:.2f} | "
                f"{g_f['psnr']:.2f} | {g_f['iou']:.3f} | {loc['psnr']:.2f} | {wall:.0f} |"
            )
            print(runs[-1], flush=True)
    print("| scene | camera lr | rotation error (deg) | centre error (% extent) | hull of the others misses (%) | s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    print("\n".join(rows))
    if runs:
        print(
            "\n| scene, corrected cameras | pose error (deg / %) | G_c | G_f | G_f IoU | G_f, test cameras localised "
            "| s |"
        )
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
        print("\n".join(runs))


if __name__ == "__main__":
    main()
