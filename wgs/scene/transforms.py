"""Blender (`transforms_{train,test}.json`) and instant-ngp / nerfstudio (`transforms.json`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.images import image_size
from .convention import c2w_opengl_to_w2c_opencv, focal_from_fov, intrinsics
from .paths import resolve_image, safe_join
from .types import Distortion, RawScene, View


def _load_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", path) from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError("expected an object with a 'frames' list", path)
    return data


def _pose(frame: dict[str, Any], path: Path, idx: int) -> np.ndarray:
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"frame {idx}: missing or malformed 'transform_matrix'", path) from None
    if m.shape not in ((4, 4), (3, 4)):
        raise InputError(f"frame {idx}: transform_matrix must be 4x4, got {m.shape}", path)
    if not np.isfinite(m).all():
        raise InputError(f"frame {idx}: transform_matrix holds NaN or inf", path)
    if np.abs(m).max() > 1e9:
        raise InputError(f"frame {idx}: transform_matrix has entries beyond 1e9", path)
    if abs(np.linalg.det(m[:3, :3])) < 1e-8:
        raise InputError(f"frame {idx}: transform_matrix is singular", path)
    return c2w_opengl_to_w2c_opencv(m)


def _num(d: dict[str, Any], key: str, path: Path, default: float | None = None) -> float:
    v = d.get(key, default)
    if v is None or isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
        raise InputError(f"missing or invalid '{key}' (a finite number is needed, got {str(v)[:40]!r})", path)
    return float(v)


def _fov(d: dict[str, Any], key: str, path: Path) -> float:
    fov = _num(d, key, path)
    if not 1e-4 <= fov <= np.pi - 1e-4:  # closer to 0 or pi the focal length is 0 or overflows
        raise InputError(f"{key} = {fov} is not a field of view in (0, pi)", path)
    return fov


def _frame(frame: Any, path: Path, idx: int) -> dict[str, Any]:
    if not isinstance(frame, dict):
        raise InputError(f"frame {idx} is not an object", path)
    if not isinstance(frame.get("file_path", ""), str):
        raise InputError(f"frame {idx}: 'file_path' must be a string", path)
    return frame


def _size(merged: dict[str, Any], key: str, actual: int, path: Path) -> int:
    """w or h from the file (default: the image's own), a positive whole number of pixels."""
    v = _num(merged, key, path, actual)
    if v != int(v) or not 1 <= v <= 1_000_000:
        raise InputError(f"'{key}' = {v} is not an image size in pixels", path)
    return int(v)


def read_blender_scene(root: Path) -> RawScene:
    """NeRF-Synthetic layout: RGBA images whose alpha is the object mask."""
    views: list[View] = []
    train: list[int] = []
    test: list[int] = []
    notes: list[str] = []
    files = []
    for split, bucket in (("train", train), ("test", test)):
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            if split == "train":
                raise InputError("missing transforms_train.json", root)
            continue
        files.append(path)
        data = _load_json(path)
        fov = _fov(data, "camera_angle_x", path)
        size: tuple[int, int] | None = None
        for i, frame in enumerate(data["frames"]):
            frame = _frame(frame, path, i)
            img = resolve_image(root, frame.get("file_path", ""), path)
            if img is None:
                notes.append(f"{path.name}: frame {i} image {frame.get('file_path')!r} is missing: skipped")
                continue
            w, h = image_size(img)
            if size is None:
                size = (w, h)
            elif (w, h) != size:
                raise InputError(f"image is {w}x{h} but the camera's other images are {size[0]}x{size[1]}", img)
            f = focal_from_fov(fov, w)
            K = intrinsics(f, f, w / 2.0, h / 2.0)
            name = f"{split}_{img.stem}{img.suffix}"
            bucket.append(len(views))
            views.append(View(name, img, K, _pose(frame, path, i), w, h))
    return RawScene(root, "blender", views, train, test, notes, files)


def read_ngp_scene(root: Path) -> RawScene:
    """instant-ngp / nerfstudio `transforms.json` (shared or per-frame intrinsics, optional masks)."""
    path = root / "transforms.json"
    data = _load_json(path)
    views: list[View] = []
    notes: list[str] = []
    for i, frame in enumerate(data["frames"]):
        frame = _frame(frame, path, i)
        merged = {**data, **frame}
        img = resolve_image(root, frame.get("file_path", ""), path)
        if img is None:
            notes.append(f"transforms.json: frame {i} image {frame.get('file_path')!r} is missing: skipped")
            continue
        img_w, img_h = image_size(img)
        w, h = _size(merged, "w", img_w, path), _size(merged, "h", img_h, path)
        if "fl_x" in merged:
            fx = _num(merged, "fl_x", path)
            fy = _num(merged, "fl_y", path, fx)
        elif "camera_angle_x" in merged:
            fx = focal_from_fov(_fov(merged, "camera_angle_x", path), w)
            fy = focal_from_fov(_fov(merged, "camera_angle_y", path), h) if "camera_angle_y" in merged else fx
        else:
            raise InputError(f"frame {i}: no focal length (fl_x or camera_angle_x)", path)
        if fx <= 0 or fy <= 0:
            raise InputError(f"frame {i}: focal length must be positive, got {fx}, {fy}", path)
        cx = _num(merged, "cx", path, w / 2.0)
        cy = _num(merged, "cy", path, h / 2.0)
        if (w, h) != (img_w, img_h):  # intrinsics given for another resolution (e.g. images_2/): rescale
            sx, sy = img_w / w, img_h / h
            fx, fy, cx, cy, w, h = fx * sx, fy * sy, cx * sx, cy * sy, img_w, img_h
        k = [_num(merged, n, path, 0.0) for n in ("k1", "k2", "p1", "p2")]
        dist = Distortion("OPENCV", [fx, fy, cx, cy, *k]) if any(k) else None
        mask = None
        if frame.get("mask_path"):
            mask = safe_join(root, frame["mask_path"], path)
            if not mask.is_file():
                raise InputError(f"frame {i}: mask file {frame['mask_path']!r} not found", path)
        views.append(
            View(
                img.relative_to(root).as_posix(),
                img,
                intrinsics(fx, fy, cx, cy),
                _pose(frame, path, i),
                w,
                h,
                mask,
                dist,
            )
        )
    return RawScene(root, "ngp", views, notes=notes, metadata_files=[path])
