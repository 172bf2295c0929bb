"""Poses for photos that have none: structure-from-motion with pycolmap on the CPU.

SIFT features (inside the masks when the photos have masks: on a turntable the background does
not move with the object), exhaustive or sequential matching, incremental mapping; the largest
model is kept and read back as a COLMAP scene. The model is written into the workspace, never
beside the photos.
"""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

from ..errors import InputError
from ..io.images import IMAGE_EXTS, find_with_stem, image_size, read_image, to_mask, write_png
from ..progress import BAR, log, progress_bar
from .native_colmap import pycolmap

MATCHERS = ("auto", "exhaustive", "sequential")
EXHAUSTIVE_UP_TO = 150  # photos; above this, sequential matching (pairs grow as n^2)
MIN_REGISTERED = 3
MIN_SHARE = 0.5  # fewer registered photos than this share: posing failed
FEW_PHOTOS = 10  # below this, say that structure-from-motion needs more overlapping photos
MAX_FEATURES = 8192
SEQUENTIAL_OVERLAP = 10  # sequential matching: each photo with its next 10 (by name)

HOW_TO_POSE = (
    "structure-from-motion needs many overlapping photos (20 or more around the object, "
    "neighbours sharing most of their view): pose a denser capture with `wgs prepare`, then train on "
    "4 of them with `--views 4` (or list them in sparse_4.txt)"
)


@dataclass
class SfmResult:
    model_dir: Path
    registered: int
    total: int
    seconds: float
    matcher: str


def find_photos(root: Path) -> tuple[Path, list[str], Path | None] | None:
    """(photo folder, photo names, mask folder or None) of a folder of unposed photos: `images/`
    (or the folder itself) holding image files, masks in `masks/` with the same stems."""
    image_dir = root / "images" if (root / "images").is_dir() else root
    names = sorted(p.name for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS)
    if not names:
        return None
    mask_dir = root / "masks" if (root / "masks").is_dir() else None
    return image_dir, names, mask_dir


def _colmap_masks(image_dir: Path, names: list[str], mask_dir: Path, out: Path) -> None:
    """COLMAP reads the mask of `a.jpg` from `a.jpg.png` (0 = no features there): write ours so."""
    for name in names:
        src = find_with_stem(mask_dir, Path(name).stem) or find_with_stem(mask_dir, name)
        if src is None:
            raise InputError(f"photo {name} has no mask (masks/ holds masks for some photos only)", mask_dir)
        m = to_mask(read_image(src))
        w, h = image_size(image_dir / name)  # the header only: the photo itself is COLMAP's to read
        if m.shape != (h, w):
            raise InputError(f"mask is {m.shape[1]}x{m.shape[0]} but its photo is {w}x{h}", src)
        r = max(2, round(0.01 * max(m.shape)))  # a margin: corners on the object's outline are good features
        grown = binary_dilation(m > 0.5, np.ones((2 * r + 1, 2 * r + 1), bool))
        write_png(out / f"{name}.png", grown.astype(np.float32))


def _count(db: Path, sql: str) -> int:
    """A row count for a progress bar. `immutable`: the reader takes no lock, which COLMAP's writer
    would otherwise die on; a torn read only costs one progress update."""
    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro&immutable=1", uri=True)) as con:
            return int(con.execute(sql).fetchone()[0])
    except sqlite3.Error:  # not created yet, or locked by the writer this instant
        return -1


@contextlib.contextmanager
def _watched(description: str, total: int, poll: Callable[[], int]) -> Iterator[None]:
    """A progress bar fed by polling `poll()` while the step runs (pycolmap releases the GIL)."""
    done = threading.Event()
    with progress_bar(description, total) as prog:

        def watch() -> None:
            while not done.wait(0.5):
                n = poll()
                if n >= 0:
                    prog.update(BAR, completed=min(n, total))

        t = threading.Thread(target=watch, daemon=True)
        t.start()
        try:
            yield
        finally:
            done.set()
            t.join()
            prog.update(BAR, completed=total)


@contextlib.contextmanager
def _colmap_quiet() -> Iterator[None]:
    """COLMAP logs every step through glog on stderr; our progress bars say it instead."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 3  # fatal only: a failure is said in our own one line
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def pose_photos(
    image_dir: Path,
    names: list[str],
    mask_dir: Path | None,
    out: Path,
    matcher: str,
    max_image_size: int,
    threads: int = 1,
) -> SfmResult:
    """Run structure-from-motion on `names` in `image_dir`; the largest model goes to `out/`
    (written whole or not at all). `matcher`: auto, exhaustive or sequential; SIFT runs on the
    photos downscaled to `max_image_size`. Raises InputError when too few photos register."""
    t0 = time.perf_counter()
    n = len(names)
    if matcher not in MATCHERS:
        raise InputError(f"unknown matcher {matcher!r}: use {', '.join(MATCHERS)}")
    if matcher == "auto":
        matcher = "exhaustive" if n <= EXHAUSTIVE_UP_TO else "sequential"
    tmp = out.parent / f".{out.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        db = tmp / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        if mask_dir is not None:
            _colmap_masks(image_dir, names, mask_dir, tmp / "masks")
            reader.mask_path = str(tmp / "masks")
        # photos of one size: one camera (better intrinsics, and views that undistort to one size)
        sizes = {image_size(image_dir / name) for name in names}
        camera_mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.AUTO
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = threads
        extraction.max_image_size = max_image_size
        extraction.sift.max_num_features = MAX_FEATURES
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = threads
        with _colmap_quiet():
            with _watched("sfm: features", n, lambda: _count(db, "SELECT COUNT(*) FROM keypoints")):
                pycolmap.extract_features(
                    db,
                    image_dir,
                    image_names=names,
                    camera_mode=camera_mode,
                    reader_options=reader,
                    extraction_options=extraction,
                    device=pycolmap.Device.cpu,
                )
            if matcher == "exhaustive":
                pairs = n * (n - 1) // 2
                with _watched(f"sfm: match ({matcher})", pairs, lambda: _count(db, "SELECT COUNT(*) FROM matches")):
                    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
            else:
                pairing = pycolmap.SequentialPairingOptions()
                pairing.overlap = SEQUENTIAL_OVERLAP
                pairing.loop_detection = False  # needs a vocabulary tree: nothing downloads
                pairs = sum(min(SEQUENTIAL_OVERLAP, n - 1 - i) for i in range(n))
                with _watched(f"sfm: match ({matcher})", pairs, lambda: _count(db, "SELECT COUNT(*) FROM matches")):
                    pycolmap.match_sequential(
                        db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
                    )
            mapping = pycolmap.IncrementalPipelineOptions()
            mapping.num_threads = threads
            mapping.random_seed = 0
            registered = [0]
            with progress_bar("sfm: register", n) as prog:

                def next_image() -> None:
                    registered[0] += 1
                    prog.update(BAR, completed=min(registered[0] + 1, n))

                models = pycolmap.incremental_mapping(
                    db, image_dir, tmp / "sparse", options=mapping, next_image_callback=next_image
                )
                best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
                prog.update(BAR, completed=best.num_reg_images() if best is not None else 0)
        n_reg = best.num_reg_images() if best is not None else 0
        if n_reg < max(MIN_REGISTERED, MIN_SHARE * n):
            hint = (
                HOW_TO_POSE
                if n < FEW_PHOTOS
                else (
                    "try photos with more overlap between neighbours, masks (masks/ beside images/) on a turntable, "
                    + ("or --matcher exhaustive" if matcher == "sequential" else "or more texture in view")
                )
            )
            raise InputError(f"structure-from-motion registered {n_reg} of {n} photos: {hint}", image_dir)
        assert best is not None  # registered enough photos
        model = tmp / "model"
        model.mkdir()
        best.write(str(model))
        if out.exists():
            shutil.rmtree(out)
        model.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    seconds = time.perf_counter() - t0
    log(f"sfm: {n_reg} of {n} photos registered ({matcher} matching) in {seconds:.1f} s")
    return SfmResult(out, n_reg, n, seconds, matcher)


__all__ = ["MATCHERS", "SfmResult", "find_photos", "pose_photos", "HOW_TO_POSE"]
