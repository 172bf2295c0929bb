"""Training/test splits: GaussianObject split files, farthest-point view selection."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .convention import look_at_center
from .types import RawScene


def read_split_file(path: Path, n_images: int) -> list[int]:
    """0-based ids (whitespace or newline separated) into the images sorted by name."""
    try:
        tokens = path.read_text(encoding="utf-8").split()
    except UnicodeDecodeError:
        raise InputError("split file is not text", path) from None
    ids = []
    for tok in tokens:
        try:
            ids.append(int(tok))
        except ValueError:
            raise InputError(f"not an image id: {tok!r}", path) from None
    bad = [i for i in ids if not 0 <= i < n_images]
    if bad:
        raise InputError(f"ids {bad} out of range: the scene has {n_images} images (ids 0..{n_images - 1})", path)
    if len(set(ids)) != len(ids):
        raise InputError("an id is listed twice", path)
    return ids


def farthest_views(centers: np.ndarray, forwards: np.ndarray, n: int) -> list[int]:
    """Pick n views spread over viewing directions (farthest-point sampling on the unit sphere of
    directions from the object centre to each camera). Deterministic: starts at view 0."""
    m = len(centers)
    if n >= m:
        return list(range(m))
    c = look_at_center(centers, forwards)
    d = centers - c
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    chosen = [0]
    dist = np.linalg.norm(d - d[0], axis=1)
    for _ in range(n - 1):
        j = int(np.argmax(dist))
        chosen.append(j)
        dist = np.minimum(dist, np.linalg.norm(d - d[j], axis=1))
    return sorted(chosen)


def choose_split(scene: RawScene, views: int | None, test_every: int) -> None:
    """Fill scene.train / scene.test in place (split files > dataset split > automatic)."""
    n_all = len(scene.views)
    sorted_ids = sorted(range(n_all), key=lambda i: scene.views[i].name)
    root = scene.root
    split_train = root / f"sparse_{views}.txt" if views else None
    split_test = root / "sparse_test.txt"
    listed_test = set(sorted_ids[i] for i in read_split_file(split_test, n_all)) if split_test.is_file() else set()
    if split_train is not None and split_train.is_file():
        scene.train = [sorted_ids[i] for i in read_split_file(split_train, n_all)]
        scene.notes.append(f"training views from {split_train.name}")
        scene.metadata_files.append(split_train)
    else:
        pool = scene.train if scene.train else [i for i in range(n_all) if i not in scene.test]
        pool = [i for i in pool if i not in listed_test]  # the listed test views are never trained on
        if views is not None and views < len(pool):
            centers = np.stack([scene.views[i].center for i in pool])
            fwd = np.stack([scene.views[i].forward for i in pool])
            scene.train = [pool[j] for j in farthest_views(centers, fwd, views)]
            scene.notes.append(f"{views} training views chosen by farthest-point sampling on camera directions")
        else:
            scene.train = list(pool)
    if split_test.is_file():
        scene.test = [sorted_ids[i] for i in read_split_file(split_test, n_all)]
        scene.metadata_files.append(split_test)
        overlap = sorted(set(scene.train) & set(scene.test))
        if overlap:
            names = ", ".join(scene.views[i].name for i in overlap[:5])
            raise InputError(f"training and test views overlap ({names}): fix the split files", split_test)
    elif not scene.test:
        rest = [i for i in sorted_ids if i not in set(scene.train)]
        scene.test = rest[::test_every] if test_every > 0 else []
        if scene.test:
            scene.notes.append(f"no test split: every {test_every}th remaining view ({len(scene.test)}) is a test view")
    else:
        scene.test = [i for i in scene.test if i not in set(scene.train)]
    if len(scene.train) < 2:
        raise InputError(f"at least 2 training views are needed, found {len(scene.train)}", root)
