"""Poses for photos that have none: structure-from-motion with pycolmap on the CPU.

A dense capture: SIFT features (inside the masks when the photos have masks: on a turntable the
background does not move with the object), exhaustive or sequential matching. A few photos far
apart: learned features and matches (`learned_matching`, as hloc feeds them to COLMAP), COLMAP's
two-view verification, and a mapper that accepts wider baselines. Then incremental mapping; the
largest model is kept and read back as a COLMAP scene. The model is written into the workspace, never
beside the photos.
"""

from __future__ import annotations

import contextlib
import itertools
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
from .learned_matching import MATCH_SIDE
from .native_colmap import pycolmap

MATCHERS = ("auto", "learned", "exhaustive", "sequential")  # as PrepareConfig.matcher's choices (a test checks)
SPARSE_UP_TO = 12  # photos; up to this many, learned matching (a sparse capture: SIFT poses few of them)
LEARNED_FALLBACK_UP_TO = (
    16  # photos; up to this many, learned matching where SIFT registers too few (n^2 pairs at ~1.5 s)
)
EXHAUSTIVE_UP_TO = 150  # photos; above this, sequential matching (pairs grow as n^2)
MIN_PAIR_INLIERS = 15  # learned matching: verified matches that join two photos
# learned matching: a photo on fewer than this share of the median photo's 3D points is left out
# (generated object: a photo 140 degrees from the others, placed 167 degrees off, had 0.11; a
# right one 45 degrees from its neighbour 0.18; counted with points three photos see only)
WEAK_IMAGE_SHARE = 0.15
# learned matching: a pair needs this many matches that LightGlue is confident of (score above
# CONFIDENT_SCORE). Wrong matches on like-looking parts of photos 60-180 degrees apart can pass
# two-view verification (40-170 of them); LightGlue is sure of at most 17 in 47 of 54 such pairs,
# while pairs whose geometry is right have 43-700 (tools/experiments/xp_pair_confidence.py)
MIN_CONFIDENT = 20
CONFIDENT_SCORE = 0.5
# learned matching: a photo with no confident pair is tried turned against the others with every
# 4th keypoint (LightGlue's cost grows as the square of the keypoints; the turn that joins is then
# matched whole)
TURN_SEARCH_STRIDE = 4
MIN_REGISTERED = 3
# the seed of COLMAP's RANSAC in two-view verification and in the mapper; left random, the same 4
# lego photos posed 1.93 or 1.94 degrees off from one run to the next, and once 5.12
RANSAC_SEED = 0
# learned matching keeps the focal length the photos' EXIF gives: it poses 4 photos closer, but
# the one whole run measured scored lower than with it refined (README, "Your own photos")
HOLD_EXIF_FOCAL = False
# learned matching: COLMAP triangulates the points only two photos see (by default it leaves them
# out). 4 photos 40-45 degrees apart: 1120-1718 points instead of 61-399 (lego 614 instead of 121),
# the median rotation error 0.78 / 0.23 / 3.55 degrees (lego 2.09) instead of 1.10 / 0.34 / 4.90
# (2.22) (`tools/experiments/xp_wide_pose.py --two-view-tracks yes|no`; README, "Your own photos")
SPARSE_TWO_VIEW_TRACKS = True
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
    for name, grown in grown_masks(image_dir, names, mask_dir).items():
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
    focal: float | None = None,
    match_side: int = MATCH_SIDE,
    hold_exif_focal: bool = HOLD_EXIF_FOCAL,
) -> SfmResult:
    """Run structure-from-motion on `names` in `image_dir`; the largest model goes to `out/`
    (written whole or not at all). `matcher`: auto (learned matching up to SPARSE_UP_TO photos,
    or where SIFT registers too few of up to LEARNED_FALLBACK_UP_TO; SIFT otherwise), learned,
    exhaustive or sequential (SIFT); SIFT runs on the photos downscaled to `max_image_size`, the
    learned features on the photos resized to a long side of `match_side`.
    `focal`: the focal length in pixels of the full photos where it is known (kept fixed).
    `hold_exif_focal`: learned matching keeps the focal length the photos' EXIF gives fixed (else
    bundle adjustment refines it from there, as on a dense capture).
    Raises InputError when too few photos pose together; leaves out, with one line each, the
    photos that do not join the others."""
    t0 = time.perf_counter()
    n = len(names)
    if matcher not in MATCHERS:
        raise InputError(f"unknown matcher {matcher!r}: use {', '.join(MATCHERS)}")
    if n < MIN_REGISTERED:
        raise InputError(f"{n} photo{'s' if n != 1 else ''}: posing needs at least {MIN_REGISTERED}", image_dir)
    chosen = matcher == "auto"
    if chosen:
        matcher = "learned" if n <= SPARSE_UP_TO else "exhaustive" if n <= EXHAUSTIVE_UP_TO else "sequential"

    def args(matcher: str) -> tuple:
        return image_dir, names, mask_dir, out, matcher, max_image_size, threads, focal, match_side, hold_exif_focal

    try:
        best = _map_photos(*args(matcher))
    except InputError:
        if not chosen or matcher == "learned" or n > LEARNED_FALLBACK_UP_TO:
            raise
        log(f"sfm: SIFT registered too few of {n} photos; trying the learned matcher")
        matcher = "learned"
        best = _map_photos(*args(matcher))
    seconds = time.perf_counter() - t0
    log(f"sfm: {best} of {n} photos registered ({matcher} matching) in {seconds:.1f} s")
    return SfmResult(out, best, n, seconds, matcher)


def _map_photos(
    image_dir: Path,
    names: list[str],
    mask_dir: Path | None,
    out: Path,
    matcher: str,
    max_image_size: int,
    threads: int,
    focal: float | None,
    match_side: int,
    hold_exif_focal: bool,
) -> int:
    """Features, matches and incremental mapping in a staging folder; the largest model moves to
    `out`. Returns how many photos it registered."""
    n = len(names)
    tmp = out.parent / f".{out.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        db = tmp / "database.db"
        reader = pycolmap.ImageReaderOptions()
        # a few photos pin down no lens distortion: a pinhole there
        reader.camera_model = "SIMPLE_PINHOLE" if matcher == "learned" else "SIMPLE_RADIAL"
        # photos of one size: one camera (better intrinsics, and views that undistort to one size)
        sizes = {image_size(image_dir / name) for name in names}
        camera_mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.AUTO
        if focal is not None:
            if len(sizes) != 1:
                raise InputError("--focal/--fov needs photos of one size", image_dir)
            (w, h) = next(iter(sizes))
            reader.camera_params = f"{focal},{w / 2},{h / 2}" + (",0" if reader.camera_model == "SIMPLE_RADIAL" else "")
        with _colmap_quiet():
            if matcher == "learned":
                verified = _learned_database(db, image_dir, names, mask_dir, reader, camera_mode, match_side)
            else:
                _sift_database(
                    db, image_dir, names, mask_dir, tmp, reader, camera_mode, matcher, max_image_size, threads
                )
                verified = {}
            sparse = matcher == "learned"
            hold = focal is not None or (sparse and hold_exif_focal and _exif_focal(db))
            best = _incremental_mapping(db, image_dir, tmp, n, threads, sparse=sparse, hold_focal=hold)
        n_reg = best.num_reg_images() if best is not None else 0
        if matcher == "learned":
            _check_sparse(best, names, verified, image_dir)
            n_reg = best.num_reg_images() if best is not None else 0
        elif n_reg < max(MIN_REGISTERED, MIN_SHARE * n):
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
    return n_reg


def _sift_database(
    db: Path,
    image_dir: Path,
    names: list[str],
    mask_dir: Path | None,
    tmp: Path,
    reader,
    camera_mode,
    matcher: str,
    max_image_size: int,
    threads: int,
) -> None:
    """SIFT features (inside the masks) and exhaustive or sequential matching into `db`."""
    n = len(names)
    if mask_dir is not None:
        _colmap_masks(image_dir, names, mask_dir, tmp / "masks")
        reader.mask_path = str(tmp / "masks")
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.max_image_size = max_image_size
    extraction.sift.max_num_features = MAX_FEATURES
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
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
            pycolmap.match_exhaustive(
                db, matching_options=matching, verification_options=verification_options(), device=pycolmap.Device.cpu
            )
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.loop_detection = False  # needs a vocabulary tree: nothing downloads
        pairs = sum(min(SEQUENTIAL_OVERLAP, n - 1 - i) for i in range(n))
        with _watched(f"sfm: match ({matcher})", pairs, lambda: _count(db, "SELECT COUNT(*) FROM matches")):
            pycolmap.match_sequential(
                db,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification_options(),
                device=pycolmap.Device.cpu,
            )


def verification_options(sparse: bool = False):
    """COLMAP's two-view geometric verification, seeded: the same photos verify, and so pose, the
    same every run. `sparse`: learned matches of a few photos far apart (more trials, fewer inliers
    accepted)."""
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = RANSAC_SEED
    if sparse:
        verification.ransac.max_num_trials = 20000
        verification.ransac.min_inlier_ratio = 0.1
        verification.min_num_inliers = MIN_PAIR_INLIERS
    return verification


def _learned_database(
    db: Path, image_dir: Path, names: list[str], mask_dir: Path | None, reader, camera_mode, side: int
) -> dict[tuple[str, str], int]:
    """Learned features (`learned_matching`, inside the grown masks, the photo at a long side of
    `side`) of every photo and matches of every pair into `db`, then COLMAP's two-view geometric
    verification. Returns each pair's verified matches."""
    from . import learned_matching as lm

    pycolmap.Database.open(db).close()  # created empty: import_images fills it
    pycolmap.import_images(db, image_dir, camera_mode, image_names=names, options=reader)
    masks = grown_masks(image_dir, names, mask_dir) if mask_dir is not None else {}
    features = []
    with progress_bar("sfm: learned features", len(names)) as prog:
        for name in names:
            features.append(lm.extract(_rgb(read_image(image_dir / name)), masks.get(name), side))
            prog.advance(BAR)
    pairs = list(itertools.combinations(range(len(names)), 2))
    found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    with progress_bar("sfm: learned matching", len(pairs)) as prog:
        for i, j in pairs:
            found[(i, j)] = lm.match(features[i], features[j])
            prog.advance(BAR)
    turns = _turned_photos(image_dir, names, masks, features, found, side)
    database = pycolmap.Database.open(db)
    try:
        ids = {im.name: im.image_id for im in database.read_all_images()}
        for name, f, k in zip(names, features, turns, strict=True):
            database.write_keypoints(ids[name], lm.turned_back(f.keypoints, f.size, k))
        confident = {}
        for (i, j), (matches, scores) in found.items():
            database.write_matches(ids[names[i]], ids[names[j]], matches)
            confident[(names[i], names[j])] = int((scores > CONFIDENT_SCORE).sum())
    finally:
        database.close()
    pair_file = db.parent / "pairs.txt"
    pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    pycolmap.verify_matches(db, pair_file, options=verification_options(sparse=True))
    database = pycolmap.Database.open(db)
    try:
        verified = {}
        for i, j in pairs:
            geometry = database.read_two_view_geometry(ids[names[i]], ids[names[j]])
            verified[(names[i], names[j])] = len(geometry.inlier_matches)
        # a pair LightGlue is sure of few matches of is wrong matches that verification could fit
        for pair, m in verified.items():
            if 0 < m and confident[pair] < MIN_CONFIDENT:
                database.delete_two_view_geometry(ids[pair[0]], ids[pair[1]])
                verified[pair] = 0
    finally:
        database.close()
    return verified


def _turned_photos(
    image_dir: Path,
    names: list[str],
    masks: dict[str, np.ndarray],
    features: list,
    found: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]],
    side: int,
) -> list[int]:
    """Photos stored turned against the others (a phone held the other way, whose EXIF orientation
    nothing here applies): the learned features are not rotation invariant. The photos joined by
    confident pairs as stored keep their frame; each other group of them is tried against those,
    its first photo turned by 0, 90, 180 and 270 degrees (every TURN_SEARCH_STRIDE-th keypoint),
    and the group and turn with the most confident matches joins them where the photo's whole
    features give at least MIN_CONFIDENT, until none does. Nothing is tried where no pair is
    confident (a capture whose photos share nothing costs no more). `features` and `found` are
    updated in place (a turned photo's features in its turned frame); returns each photo's quarter
    turns."""
    from . import learned_matching as lm

    def confident(pair_matches: tuple[np.ndarray, np.ndarray]) -> int:
        return int((pair_matches[1] > CONFIDENT_SCORE).sum())

    def thinned(f):
        return lm.Features(f.keypoints[::TURN_SEARCH_STRIDE], f.descriptors[::TURN_SEARCH_STRIDE], f.size)

    def ordered(i: int, fi, j: int, fj) -> tuple[np.ndarray, np.ndarray]:
        return lm.match(fi, fj) if i < j else lm.match(fj, fi)

    n = len(names)
    turns = [0] * n
    strong = [pair for pair, m in found.items() if confident(m) >= MIN_CONFIDENT]
    if not strong:
        return turns
    # the stored frame: the photos confidently joined, as stored, to the most confident pair
    first: tuple[int, int] = max(strong, key=lambda pair: confident(found[pair]))
    joined = set(first)
    while grown := {i for pair in strong if set(pair) & joined for i in pair} - joined:
        joined |= grown
    candidates: dict[tuple[int, int], lm.Features] = {}
    searched: dict[tuple[int, int, int], int] = {}  # (photo, turn, joined photo): confident matches, thinned

    def candidate(i: int, k: int):
        if (i, k) not in candidates:
            mask = masks.get(names[i])
            candidates[(i, k)] = (
                features[i]
                if k == 0
                else lm.extract(
                    np.rot90(_rgb(read_image(image_dir / names[i])), k),
                    None if mask is None else np.rot90(mask, k),
                    side,
                )
            )
        return candidates[(i, k)]

    def search(i: int, k: int, j: int) -> int:
        if (i, k, j) not in searched:
            searched[(i, k, j)] = confident(ordered(i, thinned(candidate(i, k)), j, thinned(features[j])))
        return searched[(i, k, j)]

    # the other photos in groups joined by confident pairs as stored: a group turns as one, and
    # its first photo is the one tried
    group = {i: [i] for i in range(n) if i not in joined}
    for a, b in strong:
        if a in group and b in group and group[a] is not group[b]:
            merged = sorted(group[a] + group[b])
            for i in merged:
                group[i] = merged
    left_out: set[int] = set()
    while rest := sorted({group[i][0] for i in group if i not in joined | left_out}):
        _, i, k = max((max(search(i, k, j) for j in joined), i, k) for i in rest for k in range(4))
        whole = {j: ordered(i, candidate(i, k), j, features[j]) for j in joined}
        if max(confident(m) for m in whole.values()) < MIN_CONFIDENT:
            left_out.update(group[i])
            continue
        for m in group[i]:  # the photo tried first, then the rest of its group, each matched whole
            whole = whole if m == i else {j: ordered(m, candidate(m, k), j, features[j]) for j in joined}
            joined.add(m)
            turns[m], features[m] = k, candidate(m, k)
            found.update({(min(m, j), max(m, j)): pair for j, pair in whole.items()})
            if k:
                log(f"sfm: {names[m]} matches the others turned by {90 * k} degrees (stored turned: posed as it is)")
    # a turned photo's pairs with the photos that did not join (those that did were matched whole
    # as they joined), matched with the features it keeps
    for i in (i for i in range(n) if turns[i]):
        for j in (j for j in range(n) if j not in joined):
            found[(min(i, j), max(i, j))] = ordered(i, features[i], j, features[j])
    return turns


def _exif_focal(db: Path) -> bool:
    """Whether every camera in `db` has its focal length from the photos' EXIF; one line says so.
    Bundle adjustment on a few photos leaves a focal it refines several per cent off (lego 4
    photos 45 degrees apart: 4.4 % long from EXIF's, 1.2 % short, and the poses 1.65 degrees off
    against 0.78 held; `tools/experiments/xp_exif_focal.py`)."""
    database = pycolmap.Database.open(db)
    try:
        cameras = database.read_all_cameras()
    finally:
        database.close()
    if not cameras or not all(c.has_prior_focal_length for c in cameras):
        return False
    focal = ", ".join(f"{c.focal_length:.0f}" for c in cameras)
    log(f"sfm: the focal length from the photos' EXIF ({focal} px at full size), held")
    return True


def _incremental_mapping(db: Path, image_dir: Path, tmp: Path, n: int, threads: int, sparse: bool, hold_focal: bool):
    """pycolmap's incremental mapper on `db`; the model with the most registered photos, or None.
    `sparse`: a few photos far apart, which COLMAP's defaults (made for dense captures) refuse.
    `hold_focal`: bundle adjustment keeps the cameras' focal lengths as the database gives them."""
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.random_seed = RANSAC_SEED
    if sparse:
        mapping.min_num_matches = MIN_PAIR_INLIERS
        mapping.mapper.init_min_num_inliers = 2 * MIN_PAIR_INLIERS
        mapping.mapper.init_min_tri_angle = 4.0
        mapping.mapper.abs_pose_min_num_inliers = MIN_PAIR_INLIERS
        mapping.mapper.abs_pose_min_inlier_ratio = 0.1
        mapping.init_num_trials = 400
        # COLMAP keeps a model of at least 0.8 of the photos: 3 of 4 would be thrown away
        mapping.min_model_size = MIN_REGISTERED
        # the points only two photos see are most of what a few photos far apart share: COLMAP
        # leaves them out by default, and bundle adjustment then has a tenth of the points
        mapping.triangulation.ignore_two_view_tracks = not SPARSE_TWO_VIEW_TRACKS
    if hold_focal:
        mapping.ba_refine_focal_length = False
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
    return best


def _check_sparse(best, names: list[str], verified: dict[tuple[str, str], int], image_dir: Path) -> None:
    """A few photos posed with learned matches: at least MIN_REGISTERED together, else one error
    that names the pairs and what they share; each photo left out gets one line."""
    posed = {im.name for im in best.images.values() if im.has_pose} if best is not None else set()
    if best is not None and posed:
        # a photo registered on far fewer 3D points than the others is most likely placed by wrong
        # matches (a photo from the far side): it is left out
        points = {im.image_id: im.num_points3D for im in best.images.values() if im.has_pose}
        typical = float(np.median(list(points.values())))
        for image_id, count in points.items():
            if count < WEAK_IMAGE_SHARE * typical:
                posed.discard(best.images[image_id].name)
                best.deregister_frame(best.images[image_id].frame_id)
    left = [name for name in names if name not in posed]
    share = sorted(verified.items(), key=lambda kv: -kv[1])
    if len(posed) < MIN_REGISTERED:
        groups = _groups(names, verified)
        shown = ", ".join(f"{a} + {b} {m}" for (a, b), m in share[:6])
        if len(groups) > 1:
            across = max(
                ((m, a, b) for (a, b), m in verified.items() if not any(a in g and b in g for g in groups)),
                default=(0, names[0], names[-1]),
            )
            where = (
                "they fall into groups that share nothing: "
                + " | ".join(", ".join(g) for g in groups)
                + f"; one more photo between {across[1]} and {across[2]} would join them"
            )
        else:
            # one group, yet no 3 posed: its pairs share points that no third photo sees
            links = [kv for kv in share if kv[1] >= 2 * MIN_PAIR_INLIERS] or share[:1]
            (a, b), _ = links[-1]
            where = (
                f"one more photo between {a} and {b}, the weakest link, would give the mapper points "
                "that three photos see"
            )
        raise InputError(
            f"no {MIN_REGISTERED} of the {len(names)} photos pose together: they share too little (verified, "
            f"confident matches per pair: {shown}; a pair needs about {2 * MIN_PAIR_INLIERS}); {where} "
            "(neighbours up to about 45 degrees apart pose)",
            image_dir,
        )
    for name in left:
        best_pair = max(
            ((m, other) for (a, b), m in verified.items() for other in (a, b) if name in (a, b) and other != name),
            default=(0, "none"),
        )
        log(
            f"sfm: {name} left out: it shares too little with the posed photos (at most {best_pair[0]} verified "
            f"matches, with {best_pair[1]}); one more photo between it and {best_pair[1]} would join it"
        )


def _groups(names: list[str], verified: dict[tuple[str, str], int]) -> list[list[str]]:
    """The photos joined by pairs with at least 2 * MIN_PAIR_INLIERS verified matches, as groups."""
    group = {name: {name} for name in names}
    for (a, b), m in verified.items():
        if m >= 2 * MIN_PAIR_INLIERS and group[a] is not group[b]:
            joined = group[a] | group[b]
            for name in joined:
                group[name] = joined
    unique = {id(g): sorted(g) for g in group.values()}
    return sorted(unique.values(), key=lambda g: (-len(g), g))


def grown_masks(image_dir: Path, names: list[str], mask_dir: Path) -> dict[str, np.ndarray]:
    """Each photo's mask [H, W] (bool), grown by a margin: corners on the outline are good features."""
    out = {}
    for name in names:
        src = find_with_stem(mask_dir, Path(name).stem) or find_with_stem(mask_dir, name)
        if src is None:
            raise InputError(f"photo {name} has no mask (masks/ holds masks for some photos only)", mask_dir)
        m = to_mask(read_image(src))
        w, h = image_size(image_dir / name)
        if m.shape != (h, w):
            raise InputError(f"mask is {m.shape[1]}x{m.shape[0]} but its photo is {w}x{h}", src)
        r = max(2, round(0.01 * max(m.shape)))
        out[name] = binary_dilation(m > 0.5, np.ones((2 * r + 1, 2 * r + 1), bool))
    return out


def _rgb(image: np.ndarray) -> np.ndarray:
    """[H, W, C] -> [H, W, 3]: grey repeated, alpha dropped."""
    if image.ndim == 2:
        image = image[..., None]
    return np.repeat(image, 3, axis=2) if image.shape[2] == 1 else image[..., :3]


__all__ = ["MATCHERS", "SfmResult", "find_photos", "grown_masks", "pose_photos", "HOW_TO_POSE"]
