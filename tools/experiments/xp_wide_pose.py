"""Photos 45-60 degrees apart: what poses a chain whose neighbours share points no third photo sees?

For 4 photos (generated, tests/photo_scene.py, 320x240 with masks: `make_photos`'s default object
and `shape_seed` 1 and 2; lego 400x400 chains, measuring only), the learned matches as
`sfm.pose_photos` writes them (ALIKED + LightGlue, COLMAP's two-view verification, the confidence
gate), then three mappers on the same database:
- incremental: COLMAP's incremental mapper with wgs's settings (what `prepare` runs);
- global: pycolmap's global mapper (GLOMAP: rotation averaging, then global positioning);
- chain: the photos placed along the strongest pairs (a maximum spanning tree), each pair's
  relative pose from its essential matrix, each new pair's scale from its points' depths in the
  photo it shares with the pairs placed before (the median ratio to the depths of placed points
  within 3 % of the image of them), then COLMAP's triangulation and bundle adjustment.
`--two-view-tracks no` has COLMAP leave out the points only two photos see, as it does by default
(wgs's sparse path triangulates them: `sfm.SPARSE_TWO_VIEW_TRACKS`). `--pixel-scale S` multiplies
the verification's and the chain's pixel thresholds (photos of 320-400 px, where COLMAP's are set
for photos of thousands). With `--known-focal` the camera's focal length
is the true one (as EXIF or `--focal` would give it) and stays fixed; else COLMAP's prior (1.2 x
the long side) and bundle adjustment refines it.

    python tools/experiments/xp_wide_pose.py [--steps 45 60] [--known-focal] [--pixel-scale 0.3]
        [--two-view-tracks no] [--lego ../shared/data/lego]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from photo_scene import make_photos  # noqa: E402
from xp_sparse_pose import lego_chain, spacing  # noqa: E402

from wgs.io.images import image_size  # noqa: E402
from wgs.scene import sfm  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402

NEAR = 0.03  # the chain's scale: placed points within this share of the image's long side
# `--pixel-scale`: COLMAP's pixel thresholds (two-view verification's 4 px, the chain's 2 px) times this
PIXEL_SCALE = [1.0]


def scaled_verification(sparse: bool = False):
    """`sfm.verification_options` with its RANSAC threshold times PIXEL_SCALE."""
    options = VERIFICATION(sparse)
    options.ransac.max_error *= PIXEL_SCALE[0]
    return options


VERIFICATION = sfm.verification_options
sfm.verification_options = scaled_verification
# `--two-view-tracks yes|no`: whether COLMAP triangulates the points only two photos see, in the
# incremental mapper and in the chain's triangulation (COLMAP's default: no; wgs's sparse path's:
# `sfm.SPARSE_TWO_VIEW_TRACKS`)
TWO_VIEW_TRACKS = [sfm.SPARSE_TWO_VIEW_TRACKS]
INCREMENTAL = pycolmap.incremental_mapping


def with_two_view_tracks(options: pycolmap.IncrementalPipelineOptions) -> pycolmap.IncrementalPipelineOptions:
    options.triangulation.ignore_two_view_tracks = not TWO_VIEW_TRACKS[0]
    return options


def incremental_mapping(db, image_dir, out, options, **kw):
    return INCREMENTAL(db, image_dir, out, options=with_two_view_tracks(options), **kw)


pycolmap.incremental_mapping = incremental_mapping


def unit_depths(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths of rays x1 [N, 3] in camera 1 and x2 in camera 2 (normalised), camera 2 = R camera 1 + t
    with |t| = 1: least squares of d2 x2 = d1 R x1 + t."""
    A = np.stack([x1 @ R.T, -x2], -1)  # [N, 3, 2]
    d = np.linalg.solve(np.einsum("nij,nik->njk", A, A), np.einsum("nij,i->nj", A, -t)[..., None])[..., 0]
    return d[:, 0], d[:, 1]


def chain_model(db: Path, image_dir: Path, names: list[str], out: Path, refine_focal: bool):
    """The chain mapper above; a pycolmap Reconstruction, or None where fewer than 3 photos join."""
    database = pycolmap.Database.open(db)
    images = {im.name: im for im in database.read_all_images()}
    cam = database.read_all_cameras()[0]
    keypoints = {n: database.read_keypoints(images[n].image_id)[:, :2].astype(np.float64) for n in names}
    inliers = {}
    for a, b in itertools.combinations(names, 2):
        matches = database.read_two_view_geometry(images[a].image_id, images[b].image_id).inlier_matches
        if len(matches) >= 2 * sfm.MIN_PAIR_INLIERS:
            inliers[(a, b)] = matches
    database.close()
    ransac = pycolmap.RANSACOptions()
    ransac.max_error, ransac.random_seed = 2.0 * PIXEL_SCALE[0], sfm.RANSAC_SEED
    relative = {}
    for (a, b), m in inliers.items():
        found = pycolmap.estimate_essential_matrix(keypoints[a][m[:, 0]], keypoints[b][m[:, 1]], cam, cam, ransac)
        if found is not None:
            pose = found["cam2_from_cam1"]
            relative[(a, b)] = (pose.rotation.matrix(), pose.translation, m[found["inlier_mask"]])
    group = {n: {n} for n in names}
    tree = []
    for a, b in sorted(relative, key=lambda p: -len(relative[p][2])):
        if group[a] is not group[b]:
            joined = group[a] | group[b]
            for n in joined:
                group[n] = joined
            tree.append((a, b))
    if max(len(g) for g in group.values()) < 3:
        return None
    weight = {n: sum(len(relative[p][2]) for p in tree if n in p) for n in names}
    root = max(sorted(names), key=lambda n: weight[n])
    K_inv = np.linalg.inv(np.array([[cam.params[0], 0, cam.params[1]], [0, cam.params[0], cam.params[2]], [0, 0, 1]]))
    R, t = {root: np.eye(3)}, {root: np.zeros(3)}
    placed: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {n: [] for n in names}  # (pixels, depths)
    todo = list(tree)
    while todo:
        edge = next((e for e in todo if (e[0] in R) != (e[1] in R)), None)
        if edge is None:
            break
        todo.remove(edge)
        Rab, tab, m = relative[edge]
        if edge[0] in R:
            i, j, Rij, tij, mi, mj = edge[0], edge[1], Rab, tab, m[:, 0], m[:, 1]
        else:
            i, j, Rij, tij, mi, mj = edge[1], edge[0], Rab.T, -Rab.T @ tab, m[:, 1], m[:, 0]
        ui, uj = keypoints[i][mi], keypoints[j][mj]
        di, dj = unit_depths(Rij, tij, np.c_[ui, np.ones(len(ui))] @ K_inv.T, np.c_[uj, np.ones(len(uj))] @ K_inv.T)
        front = (di > 0) & (dj > 0)
        ui, uj, di, dj = ui[front], uj[front], di[front], dj[front]
        scale = 1.0
        if placed[i]:
            px = np.concatenate([p for p, _ in placed[i]])
            depth = np.concatenate([d for _, d in placed[i]])
            ratios = []
            for u, d in zip(ui, di, strict=True):
                near = np.linalg.norm(px - u, axis=1) < NEAR * max(cam.width, cam.height)
                if near.any():
                    ratios.append(np.median(depth[near]) / d)
            scale = float(np.median(ratios)) if len(ratios) >= 10 else float(np.median(depth) / np.median(di))
        R[j], t[j] = Rij @ R[i], Rij @ t[i] + scale * tij
        placed[i].append((ui, scale * di))
        placed[j].append((uj, scale * dj))
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(cam)
    for n in names:
        image = pycolmap.Image(name=n, camera_id=cam.camera_id, image_id=images[n].image_id)
        if n in R:
            model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R[n]), t[n]))
        else:
            model.add_image_with_trivial_frame(image)
    out.mkdir(parents=True, exist_ok=True)
    model = pycolmap.triangulate_points(
        model, db, image_dir, out, options=with_two_view_tracks(pycolmap.IncrementalPipelineOptions())
    )
    adjust = pycolmap.BundleAdjustmentOptions()
    adjust.refine_focal_length = refine_focal
    pycolmap.bundle_adjustment(model, adjust)
    return model


def scored(model, truth: dict[str, np.ndarray]) -> str:
    """'posed, median rotation, median centre, focal' after a similarity alignment to `truth`."""
    if model is None:
        return "none"
    posed = {}
    for im in model.images.values():
        if im.has_pose:
            posed[im.name] = np.vstack([im.cam_from_world().matrix(), [0, 0, 0, 1]])
    if len(posed) < 3:
        return f"{len(posed)} posed"
    keys = sorted(posed)
    err = pose_errors(np.stack([posed[k] for k in keys]), np.stack([truth[k] for k in keys]))
    focal = next(iter(model.cameras.values())).params[0]
    return (
        f"{len(posed)}, {np.median(err['rotation_deg']):.2f} deg, {100 * np.median(err['center']):.1f} %, "
        f"f {focal:.0f}, {model.num_points3D()} points"
    )


def learned_database(folder: Path, focal: float | None):
    """The learned matches of the photos in `folder` as `sfm.pose_photos` writes them, in
    `folder/work/database.db` (the focal fixed where given). (work, db, image_dir, names, verified)."""
    image_dir, names, mask_dir = sfm.find_photos(folder)
    work = folder / "work"
    work.mkdir()
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    if focal is not None:
        w, h = image_size(image_dir / names[0])
        reader.camera_params = f"{focal},{w / 2},{h / 2}"
    with sfm._colmap_quiet():
        verified = sfm._learned_database(
            db, image_dir, names, mask_dir, reader, pycolmap.CameraMode.SINGLE, sfm.MATCH_SIDE
        )
    return work, db, image_dir, names, verified


def compare(folder: Path, truth: dict[str, np.ndarray], focal: float | None) -> dict[str, str]:
    work, db, image_dir, names, verified = learned_database(folder, focal)
    with sfm._colmap_quiet():
        incremental = sfm._incremental_mapping(db, image_dir, work, len(names), 1, True, focal is not None)
        options = pycolmap.GlobalPipelineOptions()
        options.random_seed, options.min_num_matches, options.min_model_size = sfm.RANSAC_SEED, sfm.MIN_PAIR_INLIERS, 3
        (work / "global").mkdir()
        found = pycolmap.global_mapping(db, image_dir, work / "global", options)
        global_model = max(found.values(), key=lambda r: r.num_reg_images(), default=None)
        chain = chain_model(db, image_dir, names, work / "chain", refine_focal=focal is None)
    pairs = ", ".join(f"{a[-5]}{b[-5]} {m}" for (a, b), m in verified.items() if m) or "none"
    return {
        "pairs": pairs,
        "incremental": scored(incremental, truth),
        "global": scored(global_model, truth),
        "chain": scored(chain, truth),
    }


def wide_scenes(tmp: Path, step: float, lego: Path) -> list[tuple[str, Path, dict[str, np.ndarray], float]]:
    """4 photos about `step` degrees apart, written under `tmp`: the three generated objects and, where
    `lego` holds NeRF-Synthetic lego, a lego chain. [(name, folder, {photo: true w2c}, true focal)]."""
    scenes = []
    for shape in (None, 1, 2):
        folder = tmp / f"generated_{shape}_{step:g}"
        cams = make_photos(folder, n=4, azimuths=[step * i for i in range(4)], shape_seed=shape)
        focal = float(next(iter(cams.values()))[0][0, 0])
        scenes.append((f"generated (shape {shape})", folder, {k: v[1] for k, v in cams.items()}, focal))
    if (lego / "transforms_train.json").is_file():
        folder = tmp / f"lego_{step:g}"
        truth = lego_chain(lego, step, folder)
        angle = json.loads((lego / "transforms_train.json").read_text())["camera_angle_x"]
        scenes.append(("lego", folder, truth, 0.5 * 400 / np.tan(0.5 * angle)))
    return scenes


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=float, nargs="+", default=[45, 60])
    ap.add_argument("--known-focal", action="store_true")
    ap.add_argument("--pixel-scale", type=float, default=1.0)
    ap.add_argument("--two-view-tracks", choices=("yes", "no"), default="yes" if sfm.SPARSE_TWO_VIEW_TRACKS else "no")
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    args = ap.parse_args()
    PIXEL_SCALE[0] = args.pixel_scale
    TWO_VIEW_TRACKS[0] = args.two_view_tracks == "yes"
    print("| photos | apart (deg) | verified pairs | incremental | global | chain |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for step in args.steps:
            for name, folder, truth, focal in wide_scenes(Path(tmp), step, args.lego):
                row = compare(folder, truth, focal if args.known_focal else None)
                print(
                    f"| {name} | {spacing(truth)} | {row['pairs']} | {row['incremental']} | {row['global']} "
                    f"| {row['chain']} |"
                )


if __name__ == "__main__":
    main()
