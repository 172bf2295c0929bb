"""`wgs prepare`: import a scene into the workspace's `scene/` folder.

Writes images and masks at working resolution, a normalised COLMAP text model (pycolmap),
the split as text files, and `scene.json`. Poses are normalised with the training cameras only.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import PrepareConfig
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
MASK_MODES = ("auto", "none")  # PrepareConfig.masks: these, or a folder of masks
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


def load_scene_for_prepare(root: str | Path, cfg: PrepareConfig, sfm_model: Path | None = None) -> RawScene:
    scene = read_scene(root, sfm_model)
    for v in scene.views:
        _check_camera(v, scene)
    choose_split(scene, cfg.views, cfg.test_every)
    if cfg.masks not in MASK_MODES:
        _masks_from_folder(scene, Path(cfg.masks))
    return scene


def _masks_from_folder(scene: RawScene, folder: Path) -> None:
    """`--masks DIR`: every training and test view's mask from DIR, by the image's name or stem."""
    if not folder.is_dir():
        raise InputError("mask folder not found (--masks takes auto, none or a folder)", folder)
    for i in scene.train + scene.test:
        v = scene.views[i]
        found = next((p for p in (find_with_stem(folder, Path(v.name).stem), find_with_stem(folder, _out_name(v)[:-4]))
                      if p is not None), None)
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


def _load_view(v: View, cfg: PrepareConfig, root: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read, check, undistort and downscale one view -> rgb [H,W,3], mask [H,W] or None, K."""
    k = cfg.downscale or 1
    small = _prescaled(v, root, k)
    img = read_image(v.image, cfg.max_pixels)
    h, w = img.shape[:2]
    if (w, h) != (v.width, v.height):
        raise InputError(f"image is {w}x{h} but its camera says {v.width}x{v.height}", v.image)
    rgb, mask = split_rgba(img)
    if v.mask is not None:
        m = read_image(v.mask, cfg.max_pixels)
        if m.shape[:2] != (h, w):
            raise InputError(f"mask is {m.shape[1]}x{m.shape[0]} but its image is {w}x{h}", v.mask)
        mask = to_mask(m)
    K = v.K
    if v.distortion is not None:
        rgb, K, extra = undistort(rgb, v.distortion, K, w, h, [mask] if mask is not None else None)
        mask = extra[0] if extra else None
    if small is not None:
        rgb = split_rgba(read_image(small, cfg.max_pixels))[0]
        sh, sw = rgb.shape[:2]
        if mask is not None:
            mask = downscale(np.zeros((h, w, 3), np.float32), mask, k)[1][:sh, :sw]
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


def prepare(scene: RawScene, cfg: PrepareConfig, out: Path) -> dict[str, Any]:
    """Write the workspace scene folder for `scene` into the stage's staging folder."""
    ids = {"train": scene.train, "test": scene.test}
    norm = normalisation_from_cameras([scene.views[i].w2c for i in scene.train])
    names, cameras, sizes, images, masks = [], {}, [], [], []
    used = set()
    for split in ("train", "test"):
        for i in ids[split]:
            v = scene.views[i]
            rgb, mask, K = _load_view(v, cfg, scene.root)
            name = _out_name(v)
            if name in used:
                raise InputError(f"two images map to the same name {name}", v.image)
            used.add(name)
            write_png(path_in(out, "images", name), rgb)
            images.append(rgb)
            masks.append(mask)
            names.append(name)
            sizes.append((rgb.shape[1], rgb.shape[0]))
            cameras[name] = Camera(torch.from_numpy(np.asarray(K, dtype=np.float64)),
                                   torch.from_numpy(np.asarray(norm.w2c_to_normalised(v.w2c), dtype=np.float64)),
                                   *sizes[-1])
    mask_info = {"source": "folder" if cfg.masks not in MASK_MODES else "given" if any(m is not None for m in masks)
                 else cfg.masks}
    judged = masks  # the masks the crop check reads: those used, or the automatic ones proposed
    if mask_info["source"] == "auto":
        from ..segment.agreement import hull_missed
        from ..segment.automask import automatic_masks, mask_sheet
        from ..threads import thread_count

        made = automatic_masks(images, [cameras[n] for n in names], cfg.mask_agreement, cfg.mask_model,
                               thread_count(), MASK_MIN_FRACTION, cfg.mask_voter_support,
                               cfg.mask_colour_ratio)
        for key in ("without_agreement", "not_voting", "network_found_nothing"):
            made.record[key] = [names[k] for k in made.record[key]]
        empty = made.record["network_found_nothing"]
        cut = made.record["cut_by_agreement"]["mean"]
        n_train = len(scene.train)
        missed = hull_missed([cameras[n] for n in names[:n_train]],
                             [torch.from_numpy(m > 0.5) for m in made.masks[:n_train]])
        made.record["training_hull_missed"] = [round(x, 4) for x in missed]
        worst = int(np.argmax(missed))
        if empty:  # the network saw no object there: the scene goes on as one without masks
            mask_info = {"source": "none", "auto_failed": f"the network found no object in {', '.join(empty)}",
                         **made.record}
        elif cut > cfg.mask_max_cut or min(m.mean() for m in made.masks) < MASK_MIN_FRACTION:
            # masks that disagree cost more than the hull gives
            mask_info = {"source": "none", "auto_failed": f"the views disagree on the object: agreement cut "
                         f"{100 * cut:.0f} % of the network's object area (over mask_max_cut "
                         f"{100 * cfg.mask_max_cut:.0f} %)", **made.record}
        elif missed[worst] > cfg.mask_max_missed:  # a mask misses part of the object: the hull would cut it
            mask_info = {"source": "none", "auto_failed": f"the training masks disagree: their hull leaves out "
                         f"{100 * missed[worst]:.0f} % of the mask of {names[worst]} (over mask_max_missed "
                         f"{100 * cfg.mask_max_missed:.0f} %)", **made.record}
        else:
            masks, mask_info = made.masks, {"source": "auto", **made.record}
        judged = made.masks
        if mask_info["source"] == "none":  # not used, but there to be corrected and given back (--masks DIR)
            for name, mask in zip(names, made.masks, strict=True):
                write_png(path_in(out, "masks_proposed", name), mask)
        write_png(path_in(out, "masks_sheet.png"), mask_sheet(images[:n_train], made.masks[:n_train]))
    mask_info["training_cropped"] = [
        n for n, m in zip(names[: len(scene.train)], judged[: len(scene.train)], strict=True)
        if m is not None and edge_share(torch.from_numpy(np.ascontiguousarray(m))) > CROP_EDGE_SHARE]
    has_mask: dict[str, bool] = {}
    for name, mask in zip(names, masks, strict=True):
        if mask is not None:
            write_png(path_in(out, "masks", name), mask)
        has_mask[name] = mask is not None
    train_names = names[: len(scene.train)]
    test_names = names[len(scene.train):]
    masked = [has_mask[n] for n in train_names]
    if any(masked) and not all(masked):
        missing = train_names[masked.index(False)]
        raise InputError(f"some training views have masks but {missing} has none", scene.root)
    write_model(path_in(out, "sparse", "cameras.txt").parent, cameras)
    atomic_write_bytes(path_in(out, "split_train.txt"), ("\n".join(train_names) + "\n").encode())
    atomic_write_bytes(path_in(out, "split_test.txt"), ("\n".join(test_names) + "\n").encode() if test_names else b"")
    res = sorted(set(sizes))
    info = {
        "format": scene.format,
        "source": str(scene.root.resolve()),
        "train_images": [scene.views[i].image.relative_to(scene.root).as_posix() for i in scene.train],
        "test_images": [scene.views[i].image.relative_to(scene.root).as_posix() for i in scene.test],
        "train_names": train_names,
        "test_names": test_names,
        "resolution": list(res[0]) if len(res) == 1 else [list(r) for r in res],
        "downscale": cfg.downscale or 1,
        "has_masks": bool(all(masked)),
        "masks": mask_info,
        "normalisation": norm.to_json(),
        "notes": scene.notes,
    }
    atomic_write_json(path_in(out, "scene.json"), info)
    return info
