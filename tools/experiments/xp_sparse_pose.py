"""Posing 4 photos without cameras (`wgs.scene.sfm.pose_photos`, learned matching) against their
true cameras, after a similarity alignment: generated photos (tests/photo_scene.py, 320x240, masks)
at azimuth steps, and NeRF-Synthetic lego (400x400, measuring only) along chains of views about a
given angle apart.

    python tools/experiments/xp_sparse_pose.py [--lego ../shared/data/lego] [--steps 30 45 60 75]
        [--shapes 1 2]   (more generated objects: make_photos's shape_seed)
"""

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
from photo_scene import make_photos  # noqa: E402

from wgs.errors import InputError  # noqa: E402
from wgs.io.images import read_image, write_png  # noqa: E402
from wgs.scene.colmap import read_colmap_scene  # noqa: E402
from wgs.scene.convention import c2w_opengl_to_w2c_opencv  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402
from wgs.scene.sfm import find_photos, pose_photos  # noqa: E402


def lego_chain(root: Path, step: float, out: Path) -> dict[str, np.ndarray]:
    """4 lego views, each about `step` degrees from the last (greedy, starting at r_0), written as
    photos on white with masks; returns {name: true w2c}."""
    meta = json.loads((root / "transforms_train.json").read_text())
    c2w = np.array([f["transform_matrix"] for f in meta["frames"]])
    dirs = c2w[:, :3, 3] / np.linalg.norm(c2w[:, :3, 3], axis=1, keepdims=True)
    chosen = [0]
    while len(chosen) < 4:
        ang = np.degrees(np.arccos(np.clip(dirs @ dirs[chosen[-1]], -1, 1)))
        near = np.degrees(np.arccos(np.clip(dirs @ dirs[chosen].T, -1, 1))).min(axis=1)
        chosen.append(int(np.argmin(np.abs(ang - step) + 1000 * (near < 0.8 * step))))
    truth = {}
    for i in chosen:
        rgba = read_image(root / (meta["frames"][i]["file_path"] + ".png"))
        name = f"r_{i}.png"
        write_png(out / "images" / name, rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]))
        write_png(out / "masks" / name, rgba[..., 3])
        truth[name] = c2w_opengl_to_w2c_opencv(c2w[i])
    return truth


def lego_focal(root: Path) -> float:
    """Lego's focal length in pixels at the size `lego_chain` writes its photos (the renders' own)."""
    meta = json.loads((root / "transforms_train.json").read_text())
    width = read_image(root / (meta["frames"][0]["file_path"] + ".png")).shape[1]
    return width / 2 / float(np.tan(meta["camera_angle_x"] / 2))


def spacing(truth: dict[str, np.ndarray]) -> str:
    """The angle between each photo and its nearest other, about the origin (degrees)."""
    centres = {k: -m[:3, :3].T @ m[:3, 3] for k, m in truth.items()}
    dirs = {k: c / np.linalg.norm(c) for k, c in centres.items()}
    near = [
        min(np.degrees(np.arccos(np.clip(d @ e, -1, 1))) for j, e in dirs.items() if j != k) for k, d in dirs.items()
    ]
    return f"{min(near):.0f}-{max(near):.0f}"


def run(scene: str, truth: dict[str, np.ndarray], folder: Path, focal: float) -> dict:
    """Pose the photos in `folder`; errors against `truth` {name: w2c} and the true focal (px)."""
    image_dir, names, mask_dir = find_photos(folder)
    t0 = time.perf_counter()
    try:
        res = pose_photos(image_dir, names, mask_dir, folder / "model", "auto", 1600, 2)
    except InputError as exc:
        return {
            "scene": scene,
            "spacing": spacing(truth),
            "posed": 0,
            "seconds": time.perf_counter() - t0,
            "note": str(exc),
        }
    posed = {v.name: v for v in read_colmap_scene(folder, folder / "model", image_dir, fmt="photos").views}
    keys = sorted(posed)
    err = pose_errors(np.stack([posed[k].w2c for k in keys]), np.stack([truth[k] for k in keys]))
    return {
        "scene": scene,
        "spacing": spacing(truth),
        "posed": res.registered,
        "seconds": res.seconds,
        "rotation_median": float(np.median(err["rotation_deg"])),
        "centre_median": float(np.median(err["center"])),
        "focal_ratio": float(np.median([posed[k].K[0, 0] for k in keys]) / focal),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    ap.add_argument("--steps", type=float, nargs="+", default=[30, 45, 60, 75])
    ap.add_argument("--shapes", type=int, nargs="*", default=[])
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for step in args.steps:
            folder = Path(tmp) / f"generated_{step:g}"
            cams = make_photos(folder, n=4, azimuths=[step * i for i in range(4)])
            focal = float(next(iter(cams.values()))[0][0, 0])
            rows.append(run(f"generated, {step:g} deg steps", {k: v[1] for k, v in cams.items()}, folder, focal))
            for shape in args.shapes:
                folder = Path(tmp) / f"generated_{shape}_{step:g}"
                cams = make_photos(folder, n=4, azimuths=[step * i for i in range(4)], shape_seed=shape)
                name = f"generated (shape {shape}), {step:g} deg steps"
                rows.append(run(name, {k: v[1] for k, v in cams.items()}, folder, focal))
            if (args.lego / "transforms_train.json").is_file():
                folder = Path(tmp) / f"lego_{step:g}"
                truth = lego_chain(args.lego, step, folder)
                rows.append(run(f"lego, {step:g} deg chain", truth, folder, lego_focal(args.lego)))
    print(
        "| scene | nearest neighbour (deg) | posed | rotation median (deg) | centre median (% extent) "
        "| focal / true | s |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        rot = f"{r['rotation_median']:.2f}" if "rotation_median" in r else "refused"
        cen = f"{100 * r['centre_median']:.1f}" if "centre_median" in r else ""
        focal = f"{r['focal_ratio']:.3f}" if "focal_ratio" in r else ""
        print(f"| {r['scene']} | {r['spacing']} | {r['posed']} of 4 | {rot} | {cen} | {focal} | {r['seconds']:.1f} |")
        if "note" in r:
            print(f"|  | {r['note']} | | | | | |")


if __name__ == "__main__":
    main()
