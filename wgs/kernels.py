"""The CPU fast path's numba kernels (`gaussians/*_numba.py`, `shape/*_numba.py`): compiled on first
use and cached on disk (`cache=True`; `NUMBA_CACHE_DIR` moves the cache), about 25 s on a 2-core
CPU. `compile_kernels` compiles them all at once on a tiny scene whose arrays have the types a run's
have, so that a first run says why it waits and then no stage stops for it (the tests check that a
whole run compiles nothing more)."""

from __future__ import annotations

import importlib
import os
import pkgutil
import time
from typing import Any

import numpy as np
import torch

KERNEL_PACKAGES = ("wgs.gaussians", "wgs.shape")


def kernels() -> list[Any]:
    """The cached numba dispatchers of every `*_numba` module, those inlined into others left out."""
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    out = []
    for package in KERNEL_PACKAGES:
        for info in pkgutil.iter_modules(importlib.import_module(package).__path__):
            if not info.name.endswith("_numba"):
                continue
            module = importlib.import_module(f"{package}.{info.name}")
            for value in vars(module).values():
                if (
                    isinstance(value, CPUDispatcher)
                    and value.__module__ == module.__name__
                    and not isinstance(value._cache, NullCache)  # type: ignore[attr-defined]
                    and value.targetoptions.get("inline") != "always"
                ):
                    out.append(value)
    return out


def cache_dir() -> str:
    """Where numba caches the kernels: under `NUMBA_CACHE_DIR`, else beside wgs's modules where they
    may be written, else in the user's cache folder (the folder holding every kernel's)."""
    try:
        return os.path.commonpath([str(k._cache._cache_path) for k in kernels()])
    except (AttributeError, ValueError):  # numba's cache internals moved
        return "numba's cache"


def cached() -> bool:
    """Whether the on-disk cache holds every kernel for this source (numba's index, which it reads
    back only while the source is unchanged); True where numba's cache cannot be read this way."""
    try:
        return all(bool(k._cache._cache_file._load_index()) for k in kernels())
    except (AttributeError, OSError):  # numba's cache internals moved: nothing to say
        return True


def _tiny_frames(size: int = 32) -> list:
    """4 views of a ball from around it, with its masks (`Frame`s, as a prepared scene's)."""
    from .scene.dataset import Frame
    from .scene.orbit import look_at

    f = 1.2 * size
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    mask = (((xs - size / 2) ** 2 + (ys - size / 2) ** 2) < (0.3 * size) ** 2).float()
    frames = []
    for i, azimuth in enumerate(np.radians([0.0, 90.0, 180.0, 270.0])):
        eye = 3.0 * np.array([np.cos(azimuth), np.sin(azimuth), 0.3])
        w2c = torch.from_numpy(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))).float()
        frames.append(Frame(K=K, viewmat=w2c, width=size, height=size, name=f"{i}.png", mask=mask))
    return frames


def compile_kernels() -> float:
    """Run every kernel once (numba compiles it, or loads it from its cache); seconds taken."""
    from .gaussians.synthetic import time_backend
    from .shape.hull import HullGrid
    from .shape.revolution import revolved
    from .shape.symmetry import mirror_check

    t0 = time.perf_counter()
    with torch.random.fork_rng():
        time_backend("numba", 32, 64, 1)  # projection and rasterizer, forward and backward
        mirror_check(_tiny_frames(), 0.0, 1.0, 8)  # the hull's votes, its silhouettes, the mirror's IoUs
        cube = HullGrid(-torch.ones(3), torch.ones(3), torch.ones(4, 4, 4, dtype=torch.bool))
        revolved(cube, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))  # the solid of revolution's test
    return time.perf_counter() - t0
