"""Camera conventions and normalisation, all in one place.

Internal: world-to-camera OpenCV 4x4 + K. Blender / nerfstudio / instant-ngp store OpenGL
camera-to-world (x right, y up, camera looks down -z); flipping the camera's y and z axes converts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import camera_center

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def c2w_opengl_to_w2c_opencv(c2w: np.ndarray) -> np.ndarray:
    """[4, 4] (or [3, 4]) OpenGL camera-to-world -> [4, 4] OpenCV world-to-camera."""
    m = np.eye(4)
    m[: c2w.shape[0], :] = c2w
    return invert_rigid(m @ GL_TO_CV)


def invert_rigid(m: np.ndarray) -> np.ndarray:
    """Inverse of a [4, 4] rotation+translation (orthonormalised first for robustness)."""
    R, t = m[:3, :3], m[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def focal_from_fov(fov: float, size: int) -> float:
    """Focal length in pixels from a full field-of-view angle (radians) across `size` pixels."""
    return 0.5 * size / np.tan(0.5 * fov)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics for an image resized by (sx, sy); pixel edges, not centres, stay aligned."""
    S = np.diag([sx, sy, 1.0])
    return S @ K


def rotation_error(R: np.ndarray) -> float:
    """How far R is from a proper rotation (max |R^T R - I|, and det)."""
    return float(max(np.abs(R.T @ R - np.eye(3)).max(), abs(np.linalg.det(R) - 1.0)))


def orthonormalise(R: np.ndarray) -> np.ndarray:
    """The nearest rotation (SVD), so slightly non-orthogonal stored poses become exact."""
    u, _, vt = np.linalg.svd(R)
    out = u @ vt
    if np.linalg.det(out) < 0:
        u[:, -1] *= -1
        out = u @ vt
    return out


@dataclass
class Normalisation:
    """world_normalised = (world - center) / scale. Derived from the training cameras only."""

    center: np.ndarray  # [3]
    scale: float

    def w2c_to_normalised(self, w2c: np.ndarray) -> np.ndarray:
        out = w2c.copy()
        out[:3, 3] = (w2c[:3, :3] @ self.center + w2c[:3, 3]) / self.scale
        return out

    def w2c_from_normalised(self, w2c: np.ndarray) -> np.ndarray:
        out = w2c.copy()
        out[:3, 3] = w2c[:3, 3] * self.scale - w2c[:3, :3] @ self.center
        return out

    def points_from_normalised(self, x: np.ndarray) -> np.ndarray:
        return x * self.scale + self.center

    def to_json(self) -> dict:
        return {"center": [float(v) for v in self.center], "scale": float(self.scale)}

    @staticmethod
    def from_json(d: dict) -> Normalisation:
        return Normalisation(np.asarray(d["center"], dtype=np.float64), float(d["scale"]))


def look_at_center(centers: np.ndarray, forwards: np.ndarray) -> np.ndarray:
    """Least-squares point nearest to all optical axes: the object centre for object captures.

    centers, forwards: [N, 3]. Falls back towards the cameras' centroid when the axes are nearly
    parallel (a small ridge term keeps the system well conditioned).
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, forwards, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    centroid = centers.mean(axis=0)
    spread = max(float(np.linalg.norm(centers - centroid, axis=1).max()), 1e-12)
    lam = 1e-6 * len(centers)
    A += lam * np.eye(3)
    b += lam * centroid
    p = np.linalg.solve(A, b)
    if not np.all(np.isfinite(p)) or np.linalg.norm(p - centroid) > 1e3 * spread:
        p = centroid + forwards.mean(axis=0) * spread
    return p


def normalisation_from_cameras(w2cs: list[np.ndarray]) -> Normalisation:
    """Centre: nearest point to the training cameras' axes; scale: their median distance to it."""
    centers = np.stack([camera_center(m) for m in w2cs])
    forwards = np.stack([m[2, :3] / np.linalg.norm(m[2, :3]) for m in w2cs])
    center = look_at_center(centers, forwards)
    scale = float(np.median(np.linalg.norm(centers - center, axis=1)))
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    return Normalisation(center, scale)
