"""IDR / NeuS object datasets (DTU, BlendedMVS): image/, mask/, cameras_sphere.npz."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.images import IMAGE_EXTS, image_size
from .types import RawScene, View


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P [3, 4] = K [R | t] -> K [3, 3] (positive diagonal, K[2,2] = 1) and w2c [4, 4]."""
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-12 * max(np.abs(M).max(), 1e-300) ** 3:
        raise ValueError("singular projection matrix")
    # RQ decomposition of M via QR of the row-reversed transpose.
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    K = flip @ r.T @ flip
    R = flip @ q.T
    S = np.diag(np.sign(np.diag(K)))  # make K's diagonal positive
    K, R = K @ S, S @ R
    scale = K[2, 2]
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:  # P is defined up to sign
        R, t = -R, -t
    K = K / scale
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t / 1.0
    return K, w2c


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())


def read_idr_scene(root: Path) -> RawScene:
    cam_file = root / "cameras_sphere.npz"
    image_dir = next((root / d for d in ("image", "images") if (root / d).is_dir()), None)
    if image_dir is None:
        raise InputError("IDR scene has no image/ or images/ folder", root)
    try:
        with open(cam_file, "rb") as fh:  # our own handle: numpy leaks its own when the zip is damaged
            z = np.load(fh, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise InputError("not an .npz archive of named matrices (a single array?)", cam_file)
            with z:
                cams = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, RuntimeError) as exc:
        raise InputError(f"cannot read camera file ({str(exc).splitlines()[0][:160]})", cam_file) from None
    images = _images(image_dir)
    mask_dir = root / "mask" if (root / "mask").is_dir() else None
    masks = _images(mask_dir) if mask_dir else []
    if mask_dir and len(masks) != len(images):
        raise InputError(f"{len(masks)} masks for {len(images)} images", mask_dir)
    views = []
    for i, img in enumerate(images):
        key = f"world_mat_{i}"
        if key not in cams:
            raise InputError(f"no '{key}' for image {img.name}", cam_file)
        P = cams[key]
        if P.dtype.kind not in "iuf" or P.shape not in ((4, 4), (3, 4)) or not np.isfinite(P).all():
            raise InputError(f"'{key}' must be a finite 4x4 matrix", cam_file)
        try:
            with np.errstate(all="ignore"):
                K, w2c = decompose_projection(P[:3, :4].astype(np.float64))
        except (ValueError, np.linalg.LinAlgError):
            raise InputError(f"'{key}' is singular", cam_file) from None
        if not (np.isfinite(K).all() and np.isfinite(w2c).all() and K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(f"'{key}' is not a camera projection K [R | t]", cam_file)
        w, h = image_size(img)
        views.append(View(img.name, img, K, w2c, w, h, masks[i] if masks else None))
    return RawScene(root, "idr", views, metadata_files=[cam_file])
