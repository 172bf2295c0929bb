"""COLMAP models through pycolmap 4.x, and the Camera <-> COLMAP conversion.

Reads `sparse/0` or `sparse/` (binary or text), writes the workspace's normalised model as text,
and undistorts images of non-pinhole camera models.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..io.images import IMAGE_EXTS, find_with_stem
from .camera import Camera
from .native_colmap import pycolmap
from .paths import safe_join
from .types import Distortion, RawScene, View

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
MODEL_FILES = ("cameras.bin", "cameras.txt")


def find_model_dir(root: Path) -> Path | None:
    for cand in (root / "sparse" / "0", root / "sparse"):
        if any((cand / f).is_file() for f in MODEL_FILES):
            return cand
    return None


def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with C++ text
        raise InputError(f"cannot read COLMAP model ({str(exc).splitlines()[0]})", model_dir) from None


def camera_K(cam: pycolmap.Camera) -> np.ndarray:
    return np.asarray(cam.calibration_matrix(), dtype=np.float64)


def read_colmap_scene(
    root: Path, model_dir: Path | None = None, image_dir: Path | None = None, fmt: str = "colmap"
) -> RawScene:
    """A COLMAP scene folder: sparse model + images/ (+ masks/). `model_dir` and `image_dir` name
    them elsewhere (photos posed by `wgs prepare`: the model in the workspace)."""
    model_dir = model_dir or find_model_dir(root)
    if model_dir is None:
        raise InputError("no COLMAP model (sparse/0 or sparse/ with cameras.bin|txt)", root)
    rec = read_reconstruction(model_dir)
    image_dir = image_dir or root / "images"
    if not image_dir.is_dir():
        raise InputError("COLMAP scene has no images/ folder", root)
    mask_dir = root / "masks" if (root / "masks").is_dir() else None
    views: list[View] = []
    notes: list[str] = []
    try:  # pycolmap decodes names lazily: bytes that are not UTF-8 fail here
        named = sorted((rec.images[i].name, i) for i in rec.images)
    except UnicodeDecodeError:
        raise InputError("image names in the model are not valid UTF-8", model_dir) from None
    for name, image_id in named:
        im = rec.images[image_id]
        if not im.has_pose:
            notes.append(f"image {name} has no pose: skipped")
            continue
        cam = rec.cameras[im.camera_id]
        path = safe_join(image_dir, name, model_dir)  # names in the model must stay inside images/
        if not path.is_file():
            notes.append(f"image {path} is missing: skipped")
            continue
        w2c = np.eye(4)
        w2c[:3, :] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        dist = None if cam.model_name in PINHOLE_MODELS else Distortion(cam.model_name, list(map(float, cam.params)))
        mask = find_with_stem(mask_dir, Path(name).stem) if mask_dir else None
        if mask_dir and mask is None:
            mask = find_with_stem(mask_dir, name)  # masks named like "a.png.png"
        views.append(View(name, path, camera_K(cam), w2c, int(cam.width), int(cam.height), mask, dist))
    files = sorted(model_dir.iterdir())
    return RawScene(root, fmt, views, notes=notes, metadata_files=files)


def undistort(
    img: np.ndarray, dist: Distortion, K: np.ndarray, width: int, height: int, extra: list[np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Undistort [H, W, C] float image (and extra [H, W] maps such as masks) to a pinhole camera.

    Returns the undistorted image, its K, and the undistorted extra maps.
    """
    cam = pycolmap.Camera(model=dist.model, width=width, height=height, params=dist.params)
    opts = pycolmap.UndistortCameraOptions()

    def run(a: np.ndarray) -> tuple[np.ndarray, pycolmap.Camera]:
        u8 = np.clip(np.rint(a * 255.0), 0, 255).astype(np.uint8)
        bm, new_cam = pycolmap.undistort_image(opts, pycolmap.Bitmap.from_array(np.ascontiguousarray(u8)), cam)
        return bm.to_array().astype(np.float32) / 255.0, new_cam

    out, new_cam = run(img[..., :3])
    rest = [run(e)[0] for e in (extra or [])]
    return out, camera_K(new_cam), rest


def camera_to_colmap(camera: Camera, camera_id: int) -> tuple[pycolmap.Camera, pycolmap.Rigid3d]:
    """A PINHOLE COLMAP camera and the image's cam_from_world pose of `camera`."""
    K, w2c = camera.K.double().numpy(), camera.viewmat.double().numpy()
    cam = pycolmap.Camera(
        camera_id=camera_id,
        model="PINHOLE",
        width=int(camera.width),
        height=int(camera.height),
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
    )
    return cam, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])


def camera_from_colmap(cam: pycolmap.Camera, image: pycolmap.Image) -> Camera:
    """The Camera (float64) of a pinhole COLMAP camera and its image's pose."""
    w2c = np.eye(4)
    w2c[:3, :] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    return Camera(torch.from_numpy(camera_K(cam)), torch.from_numpy(w2c), int(cam.width), int(cam.height))


def write_model(model_dir: Path, cameras: dict[str, Camera]) -> None:
    """Write a text COLMAP model (one PINHOLE camera per image, named by the keys) with pycolmap."""
    rec = pycolmap.Reconstruction()
    for i, (name, camera) in enumerate(cameras.items(), start=1):
        cam, pose = camera_to_colmap(camera, i)
        rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=i, image_id=i), pose)
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(model_dir))


def read_model(model_dir: Path) -> dict[str, Camera]:
    """{image name: Camera} of a model written by `write_model`."""
    rec = read_reconstruction(model_dir)
    return {im.name: camera_from_colmap(rec.cameras[im.camera_id], im) for im in rec.images.values()}


def project_point(model_dir: Path, name: str, point: np.ndarray) -> np.ndarray:
    """pycolmap's own projection of a world point into image `name` (the tests' oracle)."""
    rec = read_reconstruction(model_dir)
    im = next(i for i in rec.images.values() if i.name == name)
    return np.asarray(im.project_point(np.asarray(point, dtype=np.float64)))


__all__ = ["find_model_dir", "read_colmap_scene", "undistort", "write_model", "read_model", "IMAGE_EXTS"]
