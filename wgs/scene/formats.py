"""Detect a scene folder's format and read it as a RawScene."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .colmap import find_model_dir, read_colmap_scene
from .idr import read_idr_scene
from .llff import read_llff_scene
from .sfm import find_photos
from .transforms import read_blender_scene, read_ngp_scene
from .types import RawScene

FORMATS = {
    "blender": "transforms_train.json (+ transforms_test.json), RGBA images",
    "ngp": "transforms.json (instant-ngp / nerfstudio)",
    "colmap": "sparse/0/ or sparse/ with cameras.bin|txt, and images/",
    "idr": "cameras_sphere.npz with image/ (or images/) and mask/",
    "llff": "poses_bounds.npy with images/ (or images_K/), optional masks/",
    "photos": "photos without poses in images/ (or the folder itself), optional masks/: posed by pycolmap",
}


def detect_format(root: Path) -> str:
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "ngp"
    if find_model_dir(root) is not None:
        return "colmap"
    if (root / "cameras_sphere.npz").is_file():
        return "idr"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    if find_photos(root) is not None:
        return "photos"
    found = sorted(p.name + ("/" if p.is_dir() else "") for p in root.iterdir())[:20]
    expected = "; ".join(f"{k}: {v}" for k, v in FORMATS.items())
    raise InputError(
        f"no known scene format. Found: {', '.join(found) or '(empty folder)'}. Expected one of {expected}", root
    )


def read_scene(root: str | Path, sfm_model: Path | None = None) -> RawScene:
    """The scene in folder `root`. Photos without poses need `sfm_model`, the COLMAP model that
    structure-from-motion made of them (`sfm.pose_photos`)."""
    root = Path(root)
    if not root.exists():
        raise InputError("scene folder not found", root)
    if not root.is_dir():
        raise InputError("not a folder", root)
    fmt = detect_format(root)
    if fmt == "photos":
        if sfm_model is None:
            raise InputError("photos without poses: `wgs prepare` poses them (structure-from-motion)", root)
        found = find_photos(root)
        if found is None:
            raise InputError("no photos found", root)
        scene = read_colmap_scene(root, sfm_model, found[0], fmt="photos")
    else:
        reader = {
            "blender": read_blender_scene,
            "ngp": read_ngp_scene,
            "colmap": read_colmap_scene,
            "idr": read_idr_scene,
            "llff": read_llff_scene,
        }[fmt]
        scene = reader(root)
    if not scene.views:
        raise InputError(f"{fmt} scene has no usable images", root)
    check_cameras(scene)
    return scene


def check_cameras(scene: RawScene) -> None:
    """Every format's cameras: finite, positive focal lengths, within 1e9 units (the rotation is checked
    later, with its own message)."""
    source = scene.metadata_files[0] if scene.metadata_files else scene.root
    for v in scene.views:
        K = v.K
        ok = (
            np.isfinite(v.w2c).all()
            and np.isfinite(K).all()
            and K[0, 0] > 0
            and K[1, 1] > 0
            and np.abs(v.w2c).max() < 1e9
        )
        if not ok:
            raise InputError(
                f"camera of {v.name} is not finite, has a focal length <= 0 or lies over 1e9 units away", source
            )
