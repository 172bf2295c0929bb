"""LLFF captures (nerf-pytorch, RegNeRF and many published object captures): `poses_bounds.npy`
beside `images/` (or only `images_K/`), optional `masks/`.

`poses_bounds.npy` is [N, 17]: a 3x5 matrix per image, row-major, whose first three columns are
the camera-to-world rotation with axes [down, right, back], the fourth the camera centre, the
fifth (height, width, focal) in pixels of the full-resolution images; then near and far bounds.
Poses follow the images sorted by name.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.images import IMAGE_EXTS, find_with_stem, image_size
from .convention import intrinsics
from .types import RawScene, View

POSES = "poses_bounds.npy"


def llff_to_w2c(pose: np.ndarray) -> np.ndarray:
    """One 3x5 LLFF pose -> world-to-camera [4, 4] (OpenCV: x right, y down, z forward)."""
    down, right, back, center = pose[:, 0], pose[:, 1], pose[:, 2], pose[:, 3]
    R_c2w = np.stack([right, down, -back], axis=1)
    w2c = np.eye(4)
    w2c[:3, :3] = R_c2w.T
    w2c[:3, 3] = -R_c2w.T @ center
    return w2c


def _image_dir(root: Path) -> Path | None:
    """images/, else the least downscaled images_K/."""
    if (root / "images").is_dir():
        return root / "images"
    scaled = sorted(
        (int(m.group(1)), p)
        for p in root.glob("images_*")
        if p.is_dir() and (m := re.fullmatch(r"images_(\d+)", p.name))
    )
    return scaled[0][1] if scaled else None


def read_llff_scene(root: Path) -> RawScene:
    path = root / POSES
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"cannot read poses ({str(exc).splitlines()[0][:160]})", path) from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.dtype.kind not in "iuf":
        raise InputError(f"expected an [N, 17] array of numbers, got {arr.shape} {arr.dtype}", path)
    if not np.isfinite(arr).all():
        raise InputError("poses hold NaN or infinite values", path)
    image_dir = _image_dir(root)
    if image_dir is None:
        raise InputError("LLFF scene has no images/ or images_K/ folder", root)
    images = sorted(p for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS)
    if len(images) != len(arr):
        raise InputError(f"{len(arr)} poses for {len(images)} images in {image_dir.name}/", path)
    mask_dir = root / "masks" if (root / "masks").is_dir() else None
    poses = arr[:, :15].reshape(-1, 3, 5).astype(np.float64)
    views = []
    for i, img in enumerate(images):
        h0, w0, f0 = poses[i, :, 4]
        if min(h0, w0, f0) <= 0:
            raise InputError(f"pose {i} ({img.name}) has a non-positive height, width or focal length", path)
        w, h = image_size(img)
        K = intrinsics(f0 * w / w0, f0 * h / h0, w / 2.0, h / 2.0)
        mask = None
        if mask_dir is not None:
            mask = find_with_stem(mask_dir, img.stem) or find_with_stem(mask_dir, img.name)
            if mask is None:
                raise InputError(f"no mask for {img.name}", mask_dir)
        views.append(View(img.name, img, K, llff_to_w2c(poses[i, :, :4]), w, h, mask))
    return RawScene(root, "llff", views, metadata_files=[path])


__all__ = ["read_llff_scene", "llff_to_w2c", "POSES"]
