"""The import of a scene into the workspace's `scene/` folder (driven by the prepare stage).

`load_views` reads, checks, undistorts and downscales the views and writes their images;
`write_prepared` writes the masks at working resolution, a normalised COLMAP text model (pycolmap),
the split as text files, and `scene.json`. Poses are normalised with the training cameras only.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..io import atomic_write_bytes, atomic_write_json, path_in
from ..io.images import downscale, find_with_stem, read_image, split_rgba, to_mask, write_png
from ..masking import edge_share
from .camera import Camera
from .colmap import undistort, write_model
from .convention import normalisation_from_cameras, orthonormalise, rotation_error, scale_intrinsics
from .formats import read_scene
from .splits import choose_split
from .types import RawScene, View

MASK_MIN_FRACTION = 1e-4  # a mask with less foreground than this is empty
# a training photo crops its object when more than this share of its frame's edge is object on its
# mask (a speck on the edge does not count)
CROP_EDGE_SHARE = 0.02


def scene_inputs_digest(scene: RawScene) -> str:
    """Hash of the metadata files' contents and the image files' sizes and mtimes."""
    h = hashlib.sha256()
    for f in scene.metadata_files:
        h.update(str(f).encode())
        h.update(f.read_bytes() if f.is_file() else b"")
    for v in scene.views:
        for p in (v.image, v.mask):
            if p is not None:
                st = p.stat()
                h.update(f"{p}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def load_scene_for_prepare(
    root: str | Path, views: int | None, test_every: int, mask_folder: Path | None = None, sfm_model: Path | None = None
) -> RawScene:
    """The scene at `root` with its cameras checked, `views` training views chosen (None: all) and
    every `test_every`-th other view for testing where it has no test split; the masks from
    `mask_folder` when given."""
    scene = read_scene(root, sfm_model)
    for v in scene.views:
        _check_camera(v, scene)
    choose_split(scene, views, test_every)
    if mask_folder is not None:
        _masks_from_folder(scene, mask_folder)
    return scene


def _masks_from_folder(scene: RawScene, folder: Path) -> None:
    """`--masks DIR`: every training and test view's mask from DIR, by the image's name or stem."""
    if not folder.is_dir():
        raise InputError("mask folder not found (--masks takes auto, none or a folder)", folder)
    for i in scene.train + scene.test:
        v = scene.views[i]
        found = next(
            (
                p
                for p in (find_with_stem(folder, Path(v.name).stem), find_with_stem(folder, _out_name(v)[:-4]))
                if p is not None
            ),
            None,
        )
        if found is None:
            raise InputError(f"no mask for {v.name} in the mask folder", folder)
        v.mask = found


def _check_camera(v: View, scene: RawScene) -> None:
    src = scene.metadata_files[0] if scene.metadata_files else scene.root
    if not (np.isfinite(v.K).all() and np.isfinite(v.w2c).all()):
        raise InputError(f"camera of {v.name} holds NaN or inf", src)
    if v.K[0, 0] <= 0 or v.K[1, 1] <= 0:
        raise InputError(f"camera of {v.name} has a zero or negative focal length", src)
    err = rotation_error(v.w2c[:3, :3])
    if err > 1e-2:
        raise InputError(f"pose of {v.name} is not a rotation (error {err:.3g}: singular or scaled)", src)
    v.w2c[:3, :3] = orthonormalise(v.w2c[:3, :3])


def _out_name(v: View) -> str:
    return Path(v.name.replace("/", "__")).stem + ".png"


def downscale_for(width: int, height: int, max_size: int) -> int:
    """The smallest integer downscale that brings a `width` x `height` photo's long side to at most `max_size` px."""
    return max(1, -(-max(width, height) // max_size))


def _prescaled(v: View, root: Path, k: int) -> Path | None:
    """COLMAP's `images_K/` copy of a pinhole view, when the scene ships one."""
    if k <= 1 or v.distortion is not None:
        return None
    cand = root / f"images_{k}" / v.name
    return cand if cand.is_file() else None


def _load_view(v: View, k: int, max_pixels: int, root: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read, check, undistort and downscale (by `k`) one view -> rgb [H,W,3], mask [H,W] or None, K."""
    small = _prescaled(v, root, k)
    img = read_image(v.image, max_pixels)
    h, w = img.shape[:2]
    if (w, h) != (v.width, v.height):
        raise InputError(f"image is {w}x{h} but its camera says {v.width}x{v.height}", v.image)
    rgb, mask = split_rgba(img)
    if v.mask is not None:
        m = read_image(v.mask, max_pixels)
        if m.shape[:2] != (h, w):
            raise InputError(f"mask is {m.shape[1]}x{m.shape[0]} but its image is {w}x{h}", v.mask)
        mask = to_mask(m)
    K = v.K
    if v.distortion is not None:
        rgb, K, extra = undistort(rgb, v.distortion, K, w, h, [mask] if mask is not None else None)
        mask = extra[0] if extra else None
    if small is not None:
        rgb = split_rgba(read_image(small, max_pixels))[0]
        sh, sw = rgb.shape[:2]
        if mask is not None:
            small_mask = downscale(np.zeros((h, w, 3), np.float32), mask, k)[1]
            assert small_mask is not None
            mask = small_mask[:sh, :sw]
            if mask.shape != (sh, sw):
                raise InputError(f"image is {sw}x{sh}, expected {w // k}x{h // k} for images_{k}/", small)
        K = scale_intrinsics(K, sw / w, sh / h)
    elif k > 1:
        rgb, mask = downscale(rgb, mask, k)
        K = scale_intrinsics(K, 1.0 / k, 1.0 / k)
    if mask is not None:
        check_mask(mask, v.mask or v.image)
    return rgb, mask, K


def check_mask(mask: np.ndarray, where: Path) -> None:
    if float((mask > 0.5).mean()) < MASK_MIN_FRACTION:
        raise InputError("mask is empty (no object pixels)", where)
    if mask.min() > 0.5:
        raise InputError("mask is all foreground (no background pixels): not a segmentation", where)


@dataclass
class LoadedViews:
    """The views at working size, training views first: their output names, images [H, W, 3] in
    [0, 1], masks [H, W] (None where the scene has none), cameras (normalised frame) by name."""

    names: list[str]
    images: list[np.ndarray]
    masks: list[np.ndarray | None]
    cameras: dict[str, Camera]
    n_train: int
    downscale: int
    normalisation: Any


def load_views(scene: RawScene, downscale: int, max_pixels: int, out: Path) -> LoadedViews:
    """Read every training and test view of `scene` at 1/`downscale` of its size and write its image
    into `out/images/`."""
    norm = normalisation_from_cameras([scene.views[i].w2c for i in scene.train])
    names, cameras, images, masks = [], {}, [], []
    for i in scene.train + scene.test:
        v = scene.views[i]
        rgb, mask, K = _load_view(v, downscale, max_pixels, scene.root)
        name = _out_name(v)
        if name in cameras:
            raise InputError(f"two images map to the same name {name}", v.image)
        write_png(path_in(out, "images", name), rgb)
        images.append(rgb)
        masks.append(mask)
        names.append(name)
        cameras[name] = Camera(
            torch.from_numpy(np.asarray(K, dtype=np.float64)),
            torch.from_numpy(np.asarray(norm.w2c_to_normalised(v.w2c), dtype=np.float64)),
            rgb.shape[1],
            rgb.shape[0],
        )
    return LoadedViews(names, images, masks, cameras, len(scene.train), downscale, norm)


def mask_share(masks: list[np.ndarray]) -> float:
    """The mean share of a photo's pixels inside its mask (`masks`: [H, W] each, 0..1): how much of
    the frame the object covers, which the training loops' time grows with (`estimate`)."""
    return round(float(np.mean([(m > 0.5).mean() for m in masks])), 4)


def given_mask_share(scene: RawScene, max_pixels: int) -> float | None:
    """`mask_share` of the training photos' given masks (a mask file, or the image's alpha) at their
    full size, before any is loaded for training: the working size's chooser counts it. None where a
    training photo has neither (its mask is yet to be made) or one cannot be read (load_views says why)."""
    masks = []
    for i in scene.train:
        v = scene.views[i]
        try:
            mask = (
                to_mask(read_image(v.mask, max_pixels))
                if v.mask is not None
                else split_rgba(read_image(v.image, max_pixels))[1]
            )
        except InputError:
            return None
        if mask is None:
            return None
        masks.append(mask)
    return mask_share(masks) if masks else None


def write_prepared(
    scene: RawScene,
    views: LoadedViews,
    masks: list[np.ndarray | None],
    mask_info: dict[str, Any],
    judged: list[np.ndarray | None],
    out: Path,
) -> dict[str, Any]:
    """Write the prepared scene into `out` (the stage's staging folder): `masks` (the ones used),
    the COLMAP model, the split and `scene.json`, whose "masks" is `mask_info` plus the training
    photos in which the object reaches the frame's edge on `judged` (the masks used, or the
    automatic ones proposed)."""
    names, n_train = views.names, views.n_train
    mask_info = dict(mask_info)
    mask_info["training_cropped"] = [
        n
        for n, m in zip(names[:n_train], judged[:n_train], strict=True)
        if m is not None and edge_share(torch.from_numpy(np.ascontiguousarray(m))) > CROP_EDGE_SHARE
    ]
    if all(m is not None for m in masks[:n_train]):
        mask_info["training_share"] = mask_share([m for m in masks[:n_train] if m is not None])
    has_mask: dict[str, bool] = {}
    for name, mask in zip(names, masks, strict=True):
        if mask is not None:
            write_png(path_in(out, "masks", name), mask)
        has_mask[name] = mask is not None
    train_names = names[:n_train]
    test_names = names[n_train:]
    masked = [has_mask[n] for n in train_names]
    if any(masked) and not all(masked):
        missing = train_names[masked.index(False)]
        raise InputError(f"some training views have masks but {missing} has none", scene.root)
    write_model(path_in(out, "sparse", "cameras.txt").parent, views.cameras)
    atomic_write_bytes(path_in(out, "split_train.txt"), ("\n".join(train_names) + "\n").encode())
    atomic_write_bytes(path_in(out, "split_test.txt"), ("\n".join(test_names) + "\n").encode() if test_names else b"")
    res = sorted({(img.shape[1], img.shape[0]) for img in views.images})
    info = {
        "format": scene.format,
        "source": str(scene.root.resolve()),
        "train_images": [scene.views[i].image.relative_to(scene.root).as_posix() for i in scene.train],
        "test_images": [scene.views[i].image.relative_to(scene.root).as_posix() for i in scene.test],
        "train_names": train_names,
        "test_names": test_names,
        "resolution": list(res[0]) if len(res) == 1 else [list(r) for r in res],
        "downscale": views.downscale,
        "has_masks": bool(all(masked)),
        "masks": mask_info,
        "normalisation": views.normalisation.to_json(),
        "notes": scene.notes,
    }
    atomic_write_json(path_in(out, "scene.json"), info)
    return info
