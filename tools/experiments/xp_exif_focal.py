"""Posing 4 photos that carry their focal length in EXIF (as a phone's do): the focal refined by
bundle adjustment from EXIF's value (COLMAP's way; `sfm.pose_photos(..., hold_exif_focal=False)`),
against EXIF's value held fixed (what wgs does). The photos are those of `xp_sparse_pose.py`
(generated objects and a lego chain about `--steps` degrees apart, with masks), written as JPEGs
whose EXIF gives the 35 mm equivalent focal length in whole millimetres, as a camera writes it
(so a per cent or two off).

    python tools/experiments/xp_exif_focal.py [--lego ../shared/data/lego] [--steps 30 45] [--shapes 1 2]
"""

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from photo_scene import as_exif_jpegs, make_photos  # noqa: E402
from xp_sparse_pose import lego_chain, lego_focal  # noqa: E402

from wgs.errors import InputError  # noqa: E402
from wgs.scene import sfm  # noqa: E402
from wgs.scene.colmap import read_colmap_scene  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402


def pose(folder: Path, truth: dict[str, np.ndarray], focal_px: float, hold: bool) -> dict:
    image_dir, names, mask_dir = sfm.find_photos(folder)
    out = folder / ("held" if hold else "refined")
    try:
        res = sfm.pose_photos(image_dir, names, mask_dir, out, "auto", 1600, 2, hold_exif_focal=hold)
    except InputError:
        return {"posed": 0}
    posed = {v.name: v for v in read_colmap_scene(folder, out, image_dir, fmt="photos").views}
    keys = sorted(posed)
    err = pose_errors(np.stack([posed[k].w2c for k in keys]), np.stack([truth[Path(k).stem] for k in keys]))
    return {
        "posed": res.registered,
        "rotation": float(np.median(err["rotation_deg"])),
        "centre": float(np.median(err["center"])),
        "focal": float(np.median([posed[k].K[0, 0] for k in keys]) / focal_px),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    ap.add_argument("--steps", type=float, nargs="+", default=[30, 45])
    ap.add_argument("--shapes", type=int, nargs="*", default=[1, 2])
    args = ap.parse_args()
    print("| photos | EXIF focal / true | focal | posed | rotation median (deg) | centre median (%) | focal / true |")
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for step in args.steps:
            cases = []
            for shape in [None, *args.shapes]:
                folder = Path(tmp) / f"generated_{shape}_{step:g}"
                cams = make_photos(folder, n=4, azimuths=[step * i for i in range(4)], shape_seed=shape)
                focal = float(next(iter(cams.values()))[0][0, 0])
                truth = {Path(k).stem: v[1] for k, v in cams.items()}
                cases.append((f"generated (shape {shape}), {step:g} deg", folder, truth, focal))
            if (args.lego / "transforms_train.json").is_file():
                folder = Path(tmp) / f"lego_{step:g}"
                truth = {Path(k).stem: v for k, v in lego_chain(args.lego, step, folder).items()}
                cases.append((f"lego, {step:g} deg chain", folder, truth, lego_focal(args.lego)))
            for name, folder, truth, focal in cases:
                exif = as_exif_jpegs(folder, focal)
                for hold in (False, True):
                    r = pose(folder, truth, focal, hold)
                    how = "held at EXIF's" if hold else "refined from EXIF's"
                    if not r["posed"]:
                        print(f"| {name} | {exif / focal:.3f} | {how} | refused | | | |")
                        continue
                    print(
                        f"| {name} | {exif / focal:.3f} | {how} | {r['posed']} of 4 | {r['rotation']:.2f} | "
                        f"{100 * r['centre']:.1f} | {r['focal']:.3f} |",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
