"""Photos 54-60 degrees apart: do the silhouettes pin down the poses that the matches leave open?

A pair with about 100 verified matches fits a wide family of poses (xp_object_prior.py). For 4
generated photos (tests/photo_scene.py, 320x240, masks, the true focal) and their verified learned
matches:
1. each pair's family: 600 translation directions, the rotation refined for each (robust Sampson
   error, Cauchy 2 px) and kept where its share of matches within 2 px is at least 0.85 of the best
   direction's and 90 % of them lie in front (one kept per 4 degrees);
2. the photos placed along a tree of pairs (the pair with the fewest poses first), each new camera's
   distance set so that its ray through its mask's centroid passes nearest the object's centre (the
   point nearest the first two such rays); a beam of 4, scored by how much of each mask the hull of
   the other photos leaves out (a 40^3 grid, masks at 1/4) plus 0.05 x the share of matches off by
   more than 2 px;
3. each of the 4 refined by Adam (150 steps, 6 degrees of freedom per camera but the first's) on the
   silhouettes' coherence (each mask's pixels 1.5-4 px inside its outline, and some deeper, must see
   the hull of the other masks along their ray: 256 depths, each mask's signed distance through a
   sigmoid of 0.75 px, masks at 1/2) plus 0.01 x the robust Sampson error of every pair.
Printed: both terms at the true cameras, and each start's rotation and centre errors (after a
similarity alignment) before and after, with its terms.

    python tools/experiments/xp_silhouette_pose.py [--steps 60]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import binary_dilation, distance_transform_edt
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[2] / "tests")]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from xp_object_prior import angle, fibonacci, front_share, rays, sampson_px, verified_pairs  # noqa: E402
from xp_wide_pose import wide_scenes  # noqa: E402

from wgs.io.images import find_with_stem, read_image, to_mask  # noqa: E402
from wgs.scene import sfm  # noqa: E402
from wgs.scene.native_colmap import pycolmap  # noqa: E402
from wgs.scene.pose_error import pose_errors  # noqa: E402

Poses = tuple[dict[int, np.ndarray], dict[int, np.ndarray]]  # rotations (world-to-camera), centres


def pair_family(K: np.ndarray, ui: np.ndarray, uj: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Step 1: (R, unit t) poses of camera j relative to i that fit the matches about as well as any."""
    f = K[0, 0]
    xi, xj = rays(K, ui), rays(K, uj)
    w, h = int(2 * K[0, 2]), int(2 * K[1, 2])
    cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h, params=[f, K[0, 2], K[1, 2]])
    ransac = pycolmap.RANSACOptions()
    ransac.max_error, ransac.random_seed = 2.0, sfm.RANSAC_SEED
    R0 = pycolmap.estimate_essential_matrix(ui, uj, cam, cam, ransac)["cam2_from_cam1"].rotation.matrix()
    found = []
    for d in fibonacci(600):
        sol = least_squares(
            lambda w, d=d: sampson_px(Rotation.from_rotvec(w).as_matrix() @ R0, d, xi, xj, f),
            np.zeros(3),
            loss="cauchy",
            f_scale=2.0,
            max_nfev=50,
        )
        R = Rotation.from_rotvec(sol.x).as_matrix() @ R0
        fit = np.abs(sol.fun) < 2.0
        if fit.sum() >= 8 and front_share(R, d, xi[fit], xj[fit]) >= 0.9:
            found.append((fit.mean(), R, d))
    top = max(s for s, _, _ in found)
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    for _, R, d in sorted((c for c in found if c[0] >= 0.85 * top), key=lambda c: -c[0]):
        if all(angle(R, Q) > 4 or np.degrees(np.arccos(np.clip(d @ e, -1, 1))) > 4 for Q, e in kept):
            kept.append((R, d))
    return kept


def centroid_ray(K: np.ndarray, mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    r = np.linalg.inv(K) @ np.array([xs.mean(), ys.mean(), 1.0])
    return r / np.linalg.norm(r)


def nearest_point(centres: list[np.ndarray], dirs: list[np.ndarray]) -> np.ndarray:
    A = sum(np.eye(3) - np.outer(u, u) for u in dirs)
    b = sum((np.eye(3) - np.outer(u, u)) @ c for c, u in zip(centres, dirs, strict=True))
    return np.linalg.solve(A, b)


def place(tree, choice, family, ray) -> tuple[dict, dict, np.ndarray] | None:
    """Step 2's placement: cameras along `tree` with family member `choice[k]` on edge k."""
    (i0, j0), (R, t) = tree[0], family[tree[0]][choice[0]]
    Rw, Cw = {i0: np.eye(3), j0: R}, {i0: np.zeros(3), j0: -R.T @ t}
    X = nearest_point([Cw[i0], Cw[j0]], [ray[i0], R.T @ ray[j0]])
    for (i, j), c in zip(tree[1:], choice[1:], strict=True):
        R, t = family[(i, j)][c]
        if i in Rw:
            new, old, Rn, tn = j, i, R @ Rw[i], t
        else:
            new, old, Rn, tn = i, j, R.T @ Rw[j], -R.T @ t
        b, u = -Rn.T @ tn, Rn.T @ ray[new]
        P = np.eye(3) - np.outer(u, u)
        s = float((P @ b) @ (P @ (X - Cw[old])) / max((P @ b) @ (P @ b), 1e-12))
        if s <= 0:
            return None
        Rw[new], Cw[new] = Rn, Cw[old] + s * b
    return Rw, Cw, X


def radius_of(Cw: dict, X: np.ndarray, sizes: list[float], f: float) -> float:
    return 0.75 * float(np.mean([np.linalg.norm(Cw[i] - X) * sizes[i] / f for i in Cw]))


def hull_cut(Rw: dict, Cw: dict, K: np.ndarray, small: list[np.ndarray], X: np.ndarray, radius: float) -> float:
    """Step 2's score: the mean share of each (1/4) mask that the hull of the others leaves out."""
    g = np.linspace(-radius, radius, 40)
    P = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + X
    Ks = K.copy()
    Ks[:2] /= 4
    ids = sorted(Rw)
    inside, pixels = {}, {}
    for i in ids:
        pc = (P - Cw[i]) @ Rw[i].T
        z = pc[:, 2]
        uv = np.floor(pc[:, :2] / np.maximum(z[:, None], 1e-9) * Ks[0, 0] + Ks[:2, 2]).astype(int)
        h, w = small[i].shape
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        inside[i] = np.zeros(len(P), bool)
        inside[i][ok] = small[i][uv[ok, 1], uv[ok, 0]]
        pixels[i] = (uv, ok)
    cuts = []
    for j in ids:
        uv, ok = pixels[j]
        sel = np.all([inside[k] for k in ids if k != j], axis=0) & ok
        cover = np.zeros_like(small[j])
        cover[uv[sel, 1], uv[sel, 0]] = True
        cuts.append((small[j] & ~binary_dilation(cover)).sum() / max(small[j].sum(), 1))
    return float(np.mean(cuts))


def match_miss(Rw: dict, Cw: dict, K: np.ndarray, pairs: dict) -> float:
    miss = []
    for (i, j), (ui, uj) in pairs.items():
        if i in Rw and j in Rw:
            R = Rw[j] @ Rw[i].T
            t = -Rw[j] @ Cw[j] + R @ (Rw[i] @ Cw[i])
            miss.append((np.abs(sampson_px(R, t, rays(K, ui), rays(K, uj), K[0, 0])) > 2).mean())
    return float(np.mean(miss))


def rotation(w: torch.Tensor) -> torch.Tensor:
    th = torch.sqrt((w * w).sum() + 1e-12)
    k = w / th
    z = torch.zeros((), dtype=w.dtype)
    Kx = torch.stack([torch.stack([z, -k[2], k[1]]), torch.stack([k[2], z, -k[0]]), torch.stack([-k[1], k[0], z])])
    return torch.eye(3, dtype=w.dtype) + torch.sin(th) * Kx + (1 - torch.cos(th)) * Kx @ Kx


class Coherence:
    """Step 3's terms on masks at 1/2: silhouette coherence and the pairs' robust Sampson error."""

    def __init__(self, K: np.ndarray, masks: list[np.ndarray], pairs: dict, K_matches: np.ndarray):
        """K: the masks' camera; pairs' pixels are of the photos, K_matches."""
        self.K = torch.tensor(K, dtype=torch.float64)
        self.h, self.w = masks[0].shape
        self.sdf = [torch.tensor(distance_transform_edt(~m) - distance_transform_edt(m))[None, None] for m in masks]
        rng = np.random.default_rng(0)
        self.samples = []
        for m in masks:
            inner = distance_transform_edt(m)
            rim, deep = np.argwhere((inner > 1.5) & (inner <= 4)), np.argwhere(inner > 4)
            picked = np.r_[
                rim[rng.choice(len(rim), min(300, len(rim)), replace=False)],
                deep[rng.choice(len(deep), min(60, len(deep)), replace=False)],
            ]
            self.samples.append(torch.tensor(picked[:, ::-1] + 0.5))
        self.pairs = [
            (i, j, torch.tensor(rays(K_matches, ui)), torch.tensor(rays(K_matches, uj)))
            for (i, j), (ui, uj) in pairs.items()
        ]

    def occupancy(self, v: int, P: torch.Tensor, R: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
        pc = (P - C) @ R.T
        z = pc[..., 2]
        uv = pc[..., :2] / z.clamp_min(1e-6)[..., None] * self.K[0, 0] + self.K[:2, 2]
        g = torch.stack([uv[..., 0] / self.w * 2 - 1, uv[..., 1] / self.h * 2 - 1], -1)
        s = F.grid_sample(self.sdf[v], g.reshape(1, 1, -1, 2), align_corners=False, padding_mode="border")
        s = s.reshape(z.shape)
        s = torch.where((g.abs() > 1).any(-1), torch.full_like(s, -5.0), s)  # off the frame: abstains
        s = torch.where(z > 0, s, torch.full_like(s, 50.0))
        return torch.sigmoid(-s / 0.75)

    def silhouettes(self, Rs: list, Cs: list, X: torch.Tensor, radius: float) -> torch.Tensor:
        out = []
        for j, uv in enumerate(self.samples):
            d = torch.cat([uv, torch.ones(len(uv), 1, dtype=uv.dtype)], 1) @ torch.linalg.inv(self.K).T
            dw = (d / d.norm(dim=1, keepdim=True)) @ Rs[j]
            depths = torch.linspace(-1.6, 1.6, 256, dtype=uv.dtype) * radius + (X - Cs[j]).norm()
            P = Cs[j] + dw[:, None, :] * depths[None, :, None]
            occ = torch.ones(P.shape[:2], dtype=uv.dtype)
            for v in range(len(Rs)):
                if v != j:
                    occ = occ * self.occupancy(v, P, Rs[v], Cs[v])
            out.append((1 - (torch.logsumexp(20 * occ, 1) / 20).clamp(max=1)).mean())
        return torch.stack(out).mean()

    def matches(self, Rs: list, Cs: list) -> torch.Tensor:
        out = []
        for i, j, xi, xj in self.pairs:
            R = Rs[j] @ Rs[i].T
            t = -Rs[j] @ Cs[j] + R @ (Rs[i] @ Cs[i])
            z = torch.zeros((), dtype=t.dtype)
            tx = torch.stack(
                [torch.stack([z, -t[2], t[1]]), torch.stack([t[2], z, -t[0]]), torch.stack([-t[1], t[0], z])]
            )
            E = tx @ R
            Ex, Etx = xi @ E.T, xj @ E
            den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
            r = self.K[0, 0] * (xj * Ex).sum(1) / den.clamp_min(1e-18).sqrt()
            out.append(torch.log1p((r / 2.0) ** 2).mean())
        return torch.stack(out).mean()


def refine(coh: Coherence, Rw: dict, Cw: dict, X: np.ndarray, radius: float) -> tuple[Poses, float, float]:
    ids = sorted(Rw)
    R0 = [torch.tensor(Rw[i]) for i in ids]
    C0 = [torch.tensor(Cw[i]) for i in ids]
    Xt = torch.tensor(X)
    D0 = float(np.mean([np.linalg.norm(Cw[i] - X) for i in ids]))
    ws = [torch.zeros(3, dtype=torch.float64, requires_grad=True) for _ in ids[1:]]
    cs = [torch.zeros(3, dtype=torch.float64, requires_grad=True) for _ in ids[1:]]
    opt = torch.optim.Adam([{"params": ws, "lr": 0.01}, {"params": cs, "lr": 0.02 * D0}])

    def poses() -> tuple[list, list]:
        return [R0[0]] + [rotation(w) @ R for w, R in zip(ws, R0[1:], strict=True)], [C0[0]] + [
            C + c for c, C in zip(cs, C0[1:], strict=True)
        ]

    for _ in range(150):
        Rs, Cs = poses()
        sil, mt = coh.silhouettes(Rs, Cs, Xt, radius), coh.matches(Rs, Cs)
        gauge = (torch.stack([(c - Xt).norm() for c in Cs]).mean() / D0 - 1) ** 2
        opt.zero_grad()
        (sil + 0.01 * mt + gauge).backward()
        opt.step()
    with torch.no_grad():
        Rs, Cs = poses()
        sil, mt = float(coh.silhouettes(Rs, Cs, Xt, radius)), float(coh.matches(Rs, Cs))
    return (
        ({i: R.numpy() for i, R in zip(ids, Rs, strict=True)}, {i: C.numpy() for i, C in zip(ids, Cs, strict=True)}),
        sil,
        mt,
    )


def errors(poses: Poses, truth: list[np.ndarray]) -> str:
    Rw, Cw = poses
    ids = sorted(Rw)
    est = np.stack([np.vstack([np.c_[Rw[i], -Rw[i] @ Cw[i]], [0, 0, 0, 1]]) for i in ids])
    e = pose_errors(est, np.stack([truth[i] for i in ids]))
    return f"rotation {np.round(e['rotation_deg'], 1)} deg, centre {np.round(100 * e['center'], 1)} %"


def study(folder: Path, truth: dict[str, np.ndarray], focal: float) -> None:
    names, mask_dir, (w, h), pairs = verified_pairs(folder)
    K = np.array([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1.0]])
    T = [truth[n] for n in names]
    masks = [to_mask(read_image(find_with_stem(mask_dir, Path(n).stem))) > 0.5 for n in names]
    small = [m.reshape(h // 4, 4, w // 4, 4).mean((1, 3)) > 0.5 for m in masks]
    half = [m.reshape(h // 2, 2, w // 2, 2).mean((1, 3)) > 0.5 for m in masks]
    sizes = [float(np.sqrt(m.sum())) for m in masks]
    ray = [centroid_ray(K, m) for m in masks]
    family = {e: pair_family(K, *pairs[e]) for e in pairs}
    order = sorted(pairs, key=lambda e: (len(family[e]), -len(pairs[e][0])))
    tree, seen = [order[0]], set(order[0])
    while joining := [e for e in order if (e[0] in seen) != (e[1] in seen)]:
        tree.append(joining[0])
        seen |= set(joining[0])
    print(f"  tree (pair: poses in its family): {', '.join(f'{i}-{j}: {len(family[(i, j)])}' for i, j in tree)}")
    beam: list[tuple[tuple[int, ...], float]] = [((c,), 0.0) for c in range(len(family[tree[0]]))]
    for k in range(1, len(tree)):
        grown = []
        for choice, _ in beam:
            for c in range(len(family[tree[k]])):
                placed = place(tree[: k + 1], (*choice, c), family, ray)
                if placed is not None:
                    Rw, Cw, X = placed
                    score = hull_cut(Rw, Cw, K, small, X, radius_of(Cw, X, sizes, K[0, 0]))
                    grown.append(((*choice, c), score + 0.05 * match_miss(Rw, Cw, K, pairs)))
        beam = sorted(grown, key=lambda g: g[1])[:4]
    Kh = K.copy()
    Kh[:2] /= 2
    for n, (choice, score) in enumerate(beam):
        placed = place(tree, choice, family, ray)
        assert placed is not None
        Rw, Cw, X = placed
        ids = sorted(Rw)
        local = {(ids.index(i), ids.index(j)): p for (i, j), p in pairs.items() if i in Rw and j in Rw}
        coh = Coherence(Kh, [half[i] for i in ids], local, K)
        radius = radius_of(Cw, X, sizes, K[0, 0])
        if n == 0:
            Rt = [torch.tensor(T[i][:3, :3]) for i in ids]
            Ct = [torch.tensor(-T[i][:3, :3].T @ T[i][:3, 3]) for i in ids]
            Xt = nearest_point([c.numpy() for c in Ct], [R.numpy().T @ ray[i] for R, i in zip(Rt, ids, strict=True)])
            rt = radius_of({i: c.numpy() for i, c in zip(ids, Ct, strict=True)}, Xt, sizes, K[0, 0])
            with torch.no_grad():
                print(
                    f"  the true cameras: silhouettes {float(coh.silhouettes(Rt, Ct, torch.tensor(Xt), rt)):.4f}, "
                    f"matches {float(coh.matches(Rt, Ct)):.3f}"
                )
        before = errors((Rw, Cw), T)
        local_poses = ({ids.index(i): Rw[i] for i in ids}, {ids.index(i): Cw[i] for i in ids})
        (Rl, Cl), sil, mt = refine(coh, *local_poses, X, radius)
        after = errors(({ids[k]: R for k, R in Rl.items()}, {ids[k]: C for k, C in Cl.items()}), T)
        print(f"  start {n + 1} (score {score:.4f}): {before} -> silhouettes {sil:.4f}, matches {mt:.3f}: {after}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=float, nargs="+", default=[60])
    args = ap.parse_args()
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        for step in args.steps:
            for name, folder, truth, focal in wide_scenes(Path(tmp), step, Path("/nonexistent")):
                print(f"{name}, {step:g}-degree steps")
                study(folder, truth, focal)


if __name__ == "__main__":
    main()
