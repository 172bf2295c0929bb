"""Neighbours 55-75 degrees apart: can the chain of pairs (`xp_wide_pose.chain_model`) pose 4 photos
where COLMAP's incremental mapper refuses, and can a pair's own matches say when to trust it?

For generated photos (tests/photo_scene.py's `make_photos`, 320x240, masks; its default object and
`shape_seed` 1, at `--radius`: 2.4 frames the object whole, 1.3-1.6 are close-ups that it runs out
of), the learned matches as `sfm.pose_photos` writes them, then per pair: verified matches, the
relative rotation's error against the truth (essential matrix, RANSAC 2 px), and its bootstrap
spread: the median angle between the rotation from all inliers and from `BOOTSTRAP` resamples of
them (with replacement). Per capture: the incremental mapper's and the chain's poses after a
similarity alignment to the truth.

    python tools/experiments/xp_chain_trust.py [--radius 2.4 1.6 1.3] [--steps 55 65 75] [--known-focal]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from photo_scene import make_photos  # noqa: E402
from xp_wide_pose import chain_model, learned_database, scored  # noqa: E402

from wgs.scene import sfm  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402

BOOTSTRAP = 12


def angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


def pair_rows(db: Path, names: list[str], truth: dict[str, np.ndarray]) -> list[str]:
    database = pycolmap.Database.open(db)
    images = {im.name: im for im in database.read_all_images()}
    cam = database.read_all_cameras()[0]
    kp = {n: database.read_keypoints(images[n].image_id)[:, :2].astype(np.float64) for n in names}
    geoms = {
        (a, b): database.read_two_view_geometry(images[a].image_id, images[b].image_id).inlier_matches
        for a, b in itertools.combinations(names, 2)
    }
    database.close()
    ransac = pycolmap.RANSACOptions()
    ransac.max_error, ransac.random_seed = 2.0, sfm.RANSAC_SEED
    rng = np.random.default_rng(0)
    rows = []
    for (a, b), m in geoms.items():
        true_rel = truth[b][:3, :3] @ truth[a][:3, :3].T
        apart = angle(np.eye(3), true_rel)
        if len(m) < 2 * sfm.MIN_PAIR_INLIERS:
            rows.append(f"{a[-5]}{b[-5]} {apart:.0f}deg {len(m)}m")
            continue
        found = pycolmap.estimate_essential_matrix(kp[a][m[:, 0]], kp[b][m[:, 1]], cam, cam, ransac)
        if found is None:
            rows.append(f"{a[-5]}{b[-5]} {apart:.0f}deg {len(m)}m none")
            continue
        rot = found["cam2_from_cam1"].rotation.matrix()
        spreads = []
        for _ in range(BOOTSTRAP):
            s = m[rng.integers(0, len(m), len(m))]
            again = pycolmap.estimate_essential_matrix(kp[a][s[:, 0]], kp[b][s[:, 1]], cam, cam, ransac)
            if again is not None:
                spreads.append(angle(rot, again["cam2_from_cam1"].rotation.matrix()))
        spread = float(np.median(spreads)) if spreads else float("nan")
        rows.append(f"{a[-5]}{b[-5]} {apart:.0f}deg {len(m)}m err {angle(rot, true_rel):.1f} spread {spread:.2f}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--radius", type=float, nargs="+", default=[2.4, 1.6, 1.3])
    ap.add_argument("--steps", type=float, nargs="+", default=[55, 65, 75])
    ap.add_argument("--shapes", type=int, nargs="+", default=[-1, 1])
    ap.add_argument("--known-focal", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for radius, step, shape in itertools.product(args.radius, args.steps, args.shapes):
            folder = Path(tmp) / f"r{radius}_{step:g}_{shape}"
            cams = make_photos(
                folder,
                n=4,
                azimuths=[step * i for i in range(4)],
                radius=radius,
                shape_seed=None if shape < 0 else shape,
            )
            truth = {k: v[1] for k, v in cams.items()}
            focal = float(next(iter(cams.values()))[0][0, 0]) if args.known_focal else None
            work, db, image_dir, names, _ = learned_database(folder, focal)
            with sfm._colmap_quiet():
                incremental = sfm._incremental_mapping(db, image_dir, work, 4, 1, True, focal is not None)
                chain = chain_model(db, image_dir, names, work / "chain", refine_focal=focal is None)
            print(f"radius {radius:g}, {step:g} deg, shape {shape}:")
            print("   pairs: " + " | ".join(pair_rows(db, names, truth)))
            print(f"   incremental: {scored(incremental, truth)}")
            print(f"   chain: {scored(chain, truth)}", flush=True)


if __name__ == "__main__":
    main()
