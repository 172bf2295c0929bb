"""Pairs for the volume model V, from the rendered corpus alone (no coarse model is trained): per
object, `subsets` random choices of 3-6 of its training views, and for each the strict hull's
cube (`shape.volume`) with V's input channels against the hull of all the object's views (training
and novel, over the whole sphere). One `<object>.npz` per object (x [K, 4, R, R, R] float16, y
[K, R, R, R] uint8, holdout); resumable.
"""

from __future__ import annotations

import json
import time
import zlib
from functools import partial
from pathlib import Path

import numpy as np
import torch

from wgs.config import resolve
from wgs.errors import InputError
from wgs.progress import log
from wgs.scene.dataset import load_prepared
from wgs.scene.splits import farthest_views
from wgs.shape.hull import visual_hull_grid
from wgs.shape.volume import cube_around, volume_inputs, volume_target
from wgs.workspace import Workspace

from .pairs import in_processes, save_object_pairs

VIEW_COUNTS = (4, 4, 4, 3, 5, 6, 4, 4)  # cycled over an object's subsets: mostly 4, as the product default
BOX_RESOLUTION = 48  # the hull that finds the cube (its box only is used)


def view_subsets(centers: np.ndarray, forwards: np.ndarray, subsets: int, rng: np.random.Generator) -> list[list[int]]:
    """Even subsets spread like `wgs prepare` picks views (farthest-point from a random start), odd
    ones at random."""
    out = []
    for k in range(subsets):
        n = min(VIEW_COUNTS[k % len(VIEW_COUNTS)], len(centers))
        perm = rng.permutation(len(centers))
        picked = farthest_views(centers[perm], forwards[perm], n) if k % 2 == 0 else range(n)
        out.append(sorted(int(perm[j]) for j in picked))
    return out


def object_volume_pairs(scene_dir: Path, work: Path, subsets: int, resolution: int) -> dict[str, np.ndarray]:
    from wgs.stages.registry import run_stage
    from wgs.stages.stage import StageEnv

    ws = Workspace(work)
    run_stage("prepare", ws, resolve("prepare", cli={}), StageEnv(torch.device("cpu"), 0, scene_dir=scene_dir))
    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    everything = scene.train + scene.test
    centers = np.stack([f.center.numpy() for f in scene.train])
    forwards = np.stack([f.viewmat[2, :3].numpy() for f in scene.train])
    rng = np.random.default_rng(zlib.crc32(scene_dir.name.encode()))
    xs, ys = [], []
    for sub in view_subsets(centers, forwards, subsets, rng):
        frames = [scene.train[j] for j in sub]
        try:
            grid = visual_hull_grid(frames, BOX_RESOLUTION, tolerate=0)
        except InputError:  # these views share no region (a thin object seen edge-on)
            continue
        box = cube_around(grid, resolution)
        xs.append(volume_inputs(frames, box).half().numpy())
        ys.append(volume_target(everything, box).to(torch.uint8).numpy())
    if not xs:
        raise InputError("no view subset has a hull", scene_dir)
    return {"x": np.stack(xs), "y": np.stack(ys)}


def build_volume_pairs(
    cache: Path,
    subsets: int = 16,
    resolution: int = 32,
    limit: int | None = None,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
) -> int:
    """Pairs for every rendered corpus object without them yet (cache/volume_pairs/)."""
    if workers > 1:
        return sum(in_processes(build_volume_pairs, workers, cache, subsets, resolution, limit))
    listed = json.loads((cache / "corpus.json").read_text())["objects"]
    made = 0
    for i, meta in enumerate(listed[:limit]):
        out = cache / "volume_pairs" / f"{meta['name']}.npz"
        if i % shard[1] != shard[0] or out.is_file():
            continue
        t0 = time.perf_counter()
        arrays = save_object_pairs(
            out,
            cache / "work" / f"volume-{meta['name']}",
            meta,
            partial(object_volume_pairs, cache / "objects" / meta["name"], subsets=subsets, resolution=resolution),
        )
        if arrays is None:
            continue
        made += 1
        log(f"volume pairs: {meta['name']} {len(arrays['x'])} subsets, {time.perf_counter() - t0:.0f} s")
    return made
