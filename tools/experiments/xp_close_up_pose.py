"""Close-ups without cameras: 4 generated photos so near the object that it runs out of them, posed
by `sfm.pose_photos`, then `wgs prepare`'s check of the poses against the masks.

The photos: tests/photo_scene.py's `make_photos` (320x240, masks, a fractal texture) at `--radius`
(the object is about 1.1 across; 2.4 frames it whole) and azimuth steps of `--steps` degrees, for
its default object and `shape_seed` 1. Printed per capture: the share of each mask's outline on
the frame's edge, how many photos posed and their errors after a similarity alignment to the true
cameras, and what `wgs prepare` said of the poses (the hull of the other photos against each mask).

    python tools/experiments/xp_close_up_pose.py [--radius 1.6 1.3] [--steps 45 55]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
from photo_scene import make_photos  # noqa: E402

from wgs.errors import InputError  # noqa: E402
from wgs.io.images import read_image, to_mask  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402
from wgs.scene.sfm import find_photos, pose_photos  # noqa: E402


def edge_share(mask: np.ndarray) -> float:
    return float(np.mean(np.r_[mask[0], mask[-1], mask[:, 0], mask[:, -1]] > 0.5))


def posed(folder: Path, truth: dict[str, np.ndarray], out: Path) -> str:
    image_dir, names, mask_dir = find_photos(folder)
    try:
        res = pose_photos(image_dir, names, mask_dir, out, "auto", 1600, 2)
    except InputError as exc:
        return f"refused ({str(exc)[:80]}...)"
    model = pycolmap.Reconstruction(out)
    est = {
        im.name: np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]]) for im in model.images.values() if im.has_pose
    }
    keys = sorted(est)
    err = pose_errors(np.stack([est[k] for k in keys]), np.stack([truth[k] for k in keys]))
    return (
        f"{len(keys)} of 4 posed, rotation median {np.median(err['rotation_deg']):.2f} (max "
        f"{np.max(err['rotation_deg']):.1f}) deg, centre {100 * np.median(err['center']):.1f} %, {res.seconds:.1f} s"
    )


def prepared(folder: Path, ws: Path) -> str:
    """What `wgs prepare` said of the poses: its line on the cameras, or its error."""
    out = subprocess.run(
        [sys.executable, "-m", "wgs", "-w", str(ws), "prepare", str(folder)], capture_output=True, text=True
    )
    text = " ".join((out.stdout + out.stderr).split())
    for key in ("error:", "cameras:"):
        if key in text:
            return text[text.index(key) :][:200]
    return "no line on the cameras"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, nargs="+", default=[1.6, 1.3])
    ap.add_argument("--steps", type=float, nargs="+", default=[45, 55])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for radius in args.radius:
            for step in args.steps:
                for shape in (None, 1):
                    folder = Path(tmp) / f"close_up_{radius}_{step:g}_{shape}"
                    cams = make_photos(
                        folder, n=4, azimuths=[step * i for i in range(4)], radius=radius, shape_seed=shape
                    )
                    masks = [to_mask(read_image(folder / "masks" / name)) for name in sorted(cams)]
                    shares = ", ".join(f"{edge_share(m):.2f}" for m in masks)
                    print(f"radius {radius:g}, {step:g}-degree steps, shape {shape}: outline on the edge {shares}")
                    model = Path(tmp) / f"model_{radius}_{step:g}_{shape}"
                    print(f"  {posed(folder, {k: v[1] for k, v in cams.items()}, model)}")
                    if model.is_dir():
                        print(f"  prepare: {prepared(folder, Path(tmp) / f'ws_{radius}_{step:g}_{shape}')}")


if __name__ == "__main__":
    main()
