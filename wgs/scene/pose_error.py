"""How far estimated camera poses are from reference poses, up to the similarity transform that
structure-from-motion cannot know (scale, rotation, translation of the whole world)."""

from __future__ import annotations

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst ~ s * R @ src + t (Umeyama 1991). src, dst: [N, 3], N >= 3.

    Returns s, R [3, 3] (a rotation, det +1), t [3].
    """
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"umeyama: matching [N >= 3, 3] point sets expected, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def camera_similarity(src_w2c: np.ndarray, dst_w2c: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity x_dst = s * R @ x_src + t that best takes the cameras src [N, 4, 4] onto dst
    [N, 4, 4] (world-to-camera, OpenCV, N >= 2) by their rotations and centres: R from the cameras'
    orientations (each dst rotation ~ src rotation @ R^T, averaged on SO(3)), then the scale and
    shift that take the src centres onto the dst ones under that R. With 4 cameras along an arc,
    the centres alone (`umeyama`) leave the arc's plane free to tilt by their errors.

    Returns s, R [3, 3], t [3]."""
    if src_w2c.shape != dst_w2c.shape or src_w2c.ndim != 3 or src_w2c.shape[1:] != (4, 4) or len(src_w2c) < 2:
        raise ValueError(f"camera_similarity: matching [N >= 2, 4, 4] cameras expected, got {src_w2c.shape}")
    M = np.einsum("nki,nkj->ij", dst_w2c[:, :3, :3], src_w2c[:, :3, :3])  # sum of dst_R^T @ src_R
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a, b = centers(src_w2c), centers(dst_w2c)
    a0, b0 = a - a.mean(0), b - b.mean(0)
    s = float(np.sum(b0 * (a0 @ R.T)) / max(float(np.sum(a0**2)), 1e-300))
    return s, R, b.mean(0) - s * R @ a.mean(0)


def centers(w2cs: np.ndarray) -> np.ndarray:
    """Camera centres [N, 3] of world-to-camera matrices [N, 4, 4]."""
    R, t = w2cs[:, :3, :3], w2cs[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)


def pose_errors(est_w2c: np.ndarray, ref_w2c: np.ndarray) -> dict[str, np.ndarray | float]:
    """Per-camera errors of est [N, 4, 4] against ref [N, 4, 4] (world-to-camera, OpenCV) after
    aligning the estimated camera centres to the reference ones.

    Returns {"rotation_deg": [N], "center": [N] (distance / reference extent), "scale": s}; the
    extent is the largest distance of a reference centre from their mean.
    """
    c_est, c_ref = centers(est_w2c), centers(ref_w2c)
    s, R, t = umeyama(c_est, c_ref)
    aligned = (s * (R @ c_est.T)).T + t
    extent = float(np.linalg.norm(c_ref - c_ref.mean(0), axis=1).max())
    # a camera's world-to-camera rotation in the reference world: R_est @ R^T
    rel = np.einsum("nij,kj->nik", est_w2c[:, :3, :3], R) @ np.transpose(ref_w2c[:, :3, :3], (0, 2, 1))
    cos = (np.trace(rel, axis1=1, axis2=2) - 1) / 2
    axis = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    sin = np.linalg.norm(axis, axis=-1) / 2  # atan2 stays exact near 0 degrees, where arccos does not
    return {
        "rotation_deg": np.degrees(np.arctan2(sin, cos)),
        "center": np.linalg.norm(aligned - c_ref, axis=1) / max(extent, 1e-12),
        "scale": s,
    }


__all__ = ["umeyama", "camera_similarity", "centers", "pose_errors"]
