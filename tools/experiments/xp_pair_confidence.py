"""Which learned matches of a pair of photos are right: for every pair of 4 photos, LightGlue's
matches, how many it is confident of (score above `sfm.CONFIDENT_SCORE`), and the relative
rotation from the essential matrix with the true intrinsics against the true one. Generated photos
(tests/photo_scene.py, 320x240, masks; `--shapes`: make_photos's shape_seed, -1 the default object)
at azimuth steps, and lego chains (400x400, measuring only).

    python tools/experiments/xp_pair_confidence.py [--steps 45 60 75] [--shapes -1 1 2] [--lego ../shared/data/lego]
"""

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import pycolmap  # noqa: E402
from photo_scene import make_photos  # noqa: E402
from xp_sparse_pose import lego_chain  # noqa: E402

from wgs.io.images import read_image  # noqa: E402
from wgs.scene import learned_matching as lm  # noqa: E402
from wgs.scene.sfm import CONFIDENT_SCORE, find_photos, grown_masks  # noqa: E402

LEGO_FOCAL = 0.5 * 400 / np.tan(0.5 * 0.6911112070083618)  # transforms_train.json's camera_angle_x


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def pairs(scene: str, folder: Path, truth: dict[str, np.ndarray], focal: float) -> list[dict]:
    image_dir, names, mask_dir = find_photos(folder)
    masks = grown_masks(image_dir, names, mask_dir) if mask_dir is not None else {}
    feats = {name: lm.extract(read_image(image_dir / name)[..., :3], masks.get(name)) for name in names}
    rows = []
    for a, b in itertools.combinations(names, 2):
        matches, scores = lm.match(feats[a], feats[b])
        w, h = feats[a].size
        cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h, params=[focal, w / 2, h / 2])
        options = pycolmap.TwoViewGeometryOptions()
        options.ransac.random_seed = 0
        pa, pb = feats[a].keypoints.astype(np.float64), feats[b].keypoints.astype(np.float64)
        geometry = pycolmap.estimate_calibrated_two_view_geometry(cam, pa, cam, pb, matches, options)
        true_rel = truth[b][:3, :3] @ truth[a][:3, :3].T
        error = float("nan")
        if len(geometry.inlier_matches) and pycolmap.estimate_two_view_geometry_pose(cam, pa, cam, pb, geometry):
            error = rotation_deg(geometry.cam2_from_cam1.rotation.matrix(), true_rel)
        rows.append(
            {
                "scene": scene,
                "pair": f"{Path(a).stem} + {Path(b).stem}",
                "apart": rotation_deg(np.eye(3), true_rel),
                "matches": len(matches),
                "confident": int((scores > CONFIDENT_SCORE).sum()),
                "inliers": len(geometry.inlier_matches),
                "error": error,
            }
        )
    return rows


def pair_scenes(
    tmp: Path, steps: list[float], shapes: list[int], lego: Path
) -> list[tuple[str, Path, dict[str, np.ndarray], float]]:
    """4 photos at each azimuth step, written under `tmp`: the generated objects (make_photos's
    shape_seed, -1 the default object) and, where `lego` holds NeRF-Synthetic lego, a lego chain.
    [(name, folder, {photo: true w2c}, true focal in px)]."""
    scenes = []
    for step in steps:
        for shape in shapes:
            folder = tmp / f"generated_{shape}_{step:g}"
            cams = make_photos(
                folder, n=4, azimuths=[step * i for i in range(4)], shape_seed=None if shape < 0 else shape
            )
            focal = float(next(iter(cams.values()))[0][0, 0])
            name = f"generated{'' if shape < 0 else f' (shape {shape})'}, {step:g} deg steps"
            scenes.append((name, folder, {k: v[1] for k, v in cams.items()}, focal))
        if (lego / "transforms_train.json").is_file():
            folder = tmp / f"lego_{step:g}"
            scenes.append((f"lego, {step:g} deg chain", folder, lego_chain(lego, step, folder), LEGO_FOCAL))
    return scenes


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=float, nargs="+", default=[45, 60, 75])
    ap.add_argument("--shapes", type=int, nargs="+", default=[-1, 1, 2])
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder, truth, focal in pair_scenes(Path(tmp), args.steps, args.shapes, args.lego):
            rows += pairs(name, folder, truth, focal)
    print("| photos | pair | apart (deg) | matches | confident | inliers (true K) | rotation error (deg) |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['scene']} | {r['pair']} | {r['apart']:.0f} | {r['matches']} | {r['confident']} | {r['inliers']} "
            f"| {r['error']:.1f} |"
        )
    right = [r["confident"] for r in rows if r["error"] <= 10]
    wrong = [r["confident"] for r in rows if not r["error"] <= 10]
    print(f"\nright pairs (within 10 deg): {len(right)}, confident matches {sorted(right)}")
    print(f"wrong or unposed pairs: {len(wrong)}, confident matches {sorted(wrong)}")


if __name__ == "__main__":
    main()
