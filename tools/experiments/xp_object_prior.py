"""Photos 45-60 degrees apart: does an object-centred prior fix the pairs that the essential matrix gets wrong?

The prior: a photo of an object shows the object's centre at its mask's centroid, at a distance
inversely proportional to the square root of the mask's area. Each camera's translation then
follows from its rotation, and a pair of photos has 3 unknowns instead of the essential matrix's 5.
For 4 photos (generated, tests/photo_scene.py, 320x240 with masks; lego chains, measuring only) and
the learned matches as `sfm.pose_photos` verifies them, with the true focal, per pair:
- how many of its verified matches fit the true relative pose within 2 px (Sampson error);
- the essential matrix's rotation error (COLMAP's RANSAC, 2 px);
- the prior's rotation error: the best of 400 camera directions around the object, refined on the
  robust Sampson error (Cauchy, 2 px), kept where 60 % of the matches lie in front;
- the prior's own error: the median Sampson error at the true rotation with the prior's
  translation, against the true translation's;
- the valley: every translation direction within 60 degrees of the true one, the rotation refined
  for it; the rotation error where the robust cost is lowest, and that cost against the cost at
  the true pose.
Then all 4 rotations from the prior's pairs (a maximum spanning tree, refined together) after a
similarity alignment to the truth.

    python tools/experiments/xp_object_prior.py [--steps 45 60] [--lego ../shared/data/lego]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

# the repository root (tools/) and tests/ (the photo generator), run as a script from anywhere
sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from xp_sparse_pose import spacing  # noqa: E402
from xp_wide_pose import wide_scenes  # noqa: E402

from wgs.io.images import find_with_stem, image_size, read_image, to_mask  # noqa: E402
from wgs.scene import sfm  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402

ROBUST_PX = 2.0


def rays(K: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.c_[u, np.ones(len(u))] @ np.linalg.inv(K).T


def sampson_px(R: np.ndarray, t: np.ndarray, xi: np.ndarray, xj: np.ndarray, f: float) -> np.ndarray:
    """Sampson errors [M] in pixels of rays xi, xj [M, 3] under cam_j = R cam_i + t."""
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    Ex, Etx = xi @ E.T, xj @ E
    den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
    return f * np.einsum("ni,ni->n", xj, Ex) / np.sqrt(np.maximum(den, 1e-18))


def robust(res: np.ndarray) -> float:
    return float(np.sum(np.log1p((res / ROBUST_PX) ** 2)))


def angle(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(A @ B.T) - 1) / 2, -1, 1))))


def fibonacci(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    return np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)


def looking_at_centre(v: np.ndarray, r: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera in direction v from the object's centre, the centre on
    its ray r, upright (world y down)."""
    z = -v
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0, 0])
    axis = np.cross([0.0, 0.0, 1.0], r)
    s = np.linalg.norm(axis)
    turn = Rotation.from_rotvec(axis / s * np.arctan2(s, r[2])).as_matrix() if s > 1e-9 else np.eye(3)
    return turn @ np.stack([x, np.cross(z, x), z])


def front_share(R: np.ndarray, t: np.ndarray, xi: np.ndarray, xj: np.ndarray) -> float:
    A = np.stack([xi @ R.T, -xj], -1)
    d = np.linalg.solve(np.einsum("nij,nik->njk", A, A) + 1e-12 * np.eye(2), np.einsum("nij,i->nj", A, -t)[..., None])
    return float(((d[:, 0, 0] > 0) & (d[:, 1, 0] > 0)).mean())


def prior_pair(ti: np.ndarray, tj: np.ndarray, xi: np.ndarray, xj: np.ndarray, f: float) -> np.ndarray | None:
    """The relative rotation under the prior (translation tj - R ti), or None."""
    Ri = looking_at_centre(-ti / np.linalg.norm(ti), ti / np.linalg.norm(ti))
    rj = tj / np.linalg.norm(tj)
    starts = sorted(
        (
            (robust(sampson_px(R, tj - R @ ti, xi, xj, f)), R)
            for v in fibonacci(400)
            for R in [looking_at_centre(v, rj) @ Ri.T]
        ),
        key=lambda c: c[0],
    )[:6]
    best, most = None, -1
    for _, R0 in starts:
        sol = least_squares(
            lambda w, R0=R0: sampson_px(
                Rotation.from_rotvec(w).as_matrix() @ R0, tj - Rotation.from_rotvec(w).as_matrix() @ R0 @ ti, xi, xj, f
            ),
            np.zeros(3),
            loss="cauchy",
            f_scale=ROBUST_PX,
        )
        R = Rotation.from_rotvec(sol.x).as_matrix() @ R0
        keep = np.abs(sol.fun) < 2 * ROBUST_PX
        if keep.sum() > most and front_share(R, tj - R @ ti, xi[keep], xj[keep]) >= 0.6:
            best, most = R, keep.sum()
    return best


def valley(Rt: np.ndarray, tt: np.ndarray, xi: np.ndarray, xj: np.ndarray, f: float) -> tuple[float, float, float]:
    """(rotation error where the robust cost is lowest, that cost, the cost at the truth) over the
    translation directions within 60 degrees of the true one."""
    tt = tt / np.linalg.norm(tt)
    best = (np.inf, 0.0)
    for d in fibonacci(2000):
        if d @ tt < np.cos(np.radians(60)):
            continue
        sol = least_squares(
            lambda w, d=d: sampson_px(Rotation.from_rotvec(w).as_matrix() @ Rt, d, xi, xj, f),
            np.zeros(3),
            loss="cauchy",
            f_scale=ROBUST_PX,
        )
        cost = robust(sol.fun)
        if cost < best[0]:
            best = (cost, float(np.degrees(np.linalg.norm(sol.x))))
    return best[1], best[0], robust(sampson_px(Rt, tt, xi, xj, f))


def verified_pairs(folder: Path) -> tuple[list[str], Path, tuple[int, int], dict[tuple[int, int], tuple]]:
    """The photos of `folder` matched and verified as `sfm.pose_photos` does (learned matching):
    (names, mask folder, (width, height), {(i, j): (pixels in i [M, 2], pixels in j [M, 2])}) for the
    pairs with at least 2 x MIN_PAIR_INLIERS verified matches."""
    image_dir, names, mask_dir = sfm.find_photos(folder)
    (folder / "work").mkdir()
    db = folder / "work" / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    with sfm._colmap_quiet():
        sfm._learned_database(db, image_dir, names, mask_dir, reader, pycolmap.CameraMode.SINGLE)
    database = pycolmap.Database.open(db)
    ims = {im.name: im for im in database.read_all_images()}
    kp = {n: database.read_keypoints(ims[n].image_id)[:, :2].astype(np.float64) for n in names}
    pairs = {}
    for i, j in itertools.combinations(range(len(names)), 2):
        m = database.read_two_view_geometry(ims[names[i]].image_id, ims[names[j]].image_id).inlier_matches
        if len(m) >= 2 * sfm.MIN_PAIR_INLIERS:
            pairs[(i, j)] = (kp[names[i]][m[:, 0]], kp[names[j]][m[:, 1]])
    database.close()
    assert mask_dir is not None
    return names, mask_dir, image_size(image_dir / names[0]), pairs


def study(folder: Path, truth: dict[str, np.ndarray], f: float) -> list[str]:
    names, mask_dir, (w, h), pairs = verified_pairs(folder)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h, params=[f, w / 2, h / 2])
    t = []
    for n in names:
        mask = to_mask(read_image(find_with_stem(mask_dir, Path(n).stem))) > 0.5
        ys, xs = np.nonzero(mask)
        ray = rays(K, np.array([[xs.mean(), ys.mean()]]))[0]
        t.append(ray / np.linalg.norm(ray) * f / np.sqrt(mask.sum()))
    T = [truth[n] for n in names]
    lines, fits = [], {}
    ransac = pycolmap.RANSACOptions()
    ransac.max_error, ransac.random_seed = 2.0, sfm.RANSAC_SEED
    for (i, j), (ui, uj) in pairs.items():
        xi, xj = rays(K, ui), rays(K, uj)
        Rt = T[j][:3, :3] @ T[i][:3, :3].T
        tt = T[j][:3, 3] - Rt @ T[i][:3, 3]
        fit_truth = float((np.abs(sampson_px(Rt, tt, xi, xj, f)) < 2).mean())
        found = pycolmap.estimate_essential_matrix(ui, uj, cam, cam, ransac)
        e_err = angle(found["cam2_from_cam1"].rotation.matrix(), Rt) if found else float("nan")
        R = prior_pair(t[i], t[j], xi, xj, f)
        if R is not None:
            fits[(i, j)] = (R, len(ui), xi, xj)
        p_err = angle(R, Rt) if R is not None else float("nan")
        at_truth = (
            np.median(np.abs(sampson_px(Rt, t[j] - Rt @ t[i], xi, xj, f))),
            np.median(np.abs(sampson_px(Rt, tt, xi, xj, f))),
        )
        v_err, v_cost, t_cost = valley(Rt, tt, xi, xj, f)
        lines.append(
            f"| {names[i][-5]}-{names[j][-5]} | {len(ui)} | {100 * fit_truth:.0f} % | {e_err:.1f} | {p_err:.1f} "
            f"| {at_truth[0]:.2f} / {at_truth[1]:.2f} px | {v_err:.1f} deg, {v_cost:.1f} / {t_cost:.1f} |"
        )
    # all rotations: the prior's pairs along a maximum spanning tree (no joint refinement)
    group = {k: {k} for k in range(len(names))}
    R = {}
    for (i, j), (Rij, _, _, _) in sorted(fits.items(), key=lambda kv: -kv[1][1]):
        if group[i] is group[j]:
            continue
        if not R:
            R[i] = np.eye(3)
        if i in R and j not in R:
            R[j] = Rij @ R[i]
        elif j in R and i not in R:
            R[i] = Rij.T @ R[j]
        joined = group[i] | group[j]
        for k in joined:
            group[k] = joined
    if len(R) >= 3:
        keys = sorted(R)
        est = np.stack([np.vstack([np.c_[R[k], t[k]], [0, 0, 0, 1]]) for k in keys])
        err = pose_errors(est, np.stack([T[k] for k in keys]))
        lines.append(
            f"| all, the prior's tree | {len(R)} posed | | | {np.median(err['rotation_deg']):.1f} median | | |"
        )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=float, nargs="+", default=[45, 60])
    ap.add_argument("--lego", type=Path, default=Path("../shared/data/lego"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for step in args.steps:
            for name, folder, truth, focal in wide_scenes(Path(tmp), step, args.lego):
                print(f"\n{name}, {spacing(truth)} degrees apart")
                print(
                    "| pair | verified | fit the truth | essential: rot. err (deg) | prior: rot. err (deg) "
                    "| prior at the true rotation / true pose | valley: lowest cost's rot. err, cost / truth's |"
                )
                print("| --- | ---: | ---: | ---: | ---: | ---: | --- |")
                print("\n".join(study(folder, truth, focal)))


if __name__ == "__main__":
    main()
