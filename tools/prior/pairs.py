"""Real corruptions for the prior: per corpus object, our own prepare + coarse stages on a few
views (chosen as `wgs prepare` chooses them), then G_c rendered at the object's novel poses and
paired with the ground-truth renders there. One `pairs.npz` per object and sparsity; resumable.

A pair file holds uint8 arrays: render [P, H, W, 3] and ref [P, H, W, 3] (on white, the way
`wgs repair` sees them), render_alpha and ref_alpha [P, H, W], the strict visual hull's
silhouette hull [P, H, W], plus its depth hull_depth [P, H, W] (float16, `shape.features`) and the
pose distance to the nearest training camera [P] (float32).
"""

from __future__ import annotations

import json
import shutil
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from wgs.config import resolve
from wgs.gaussians.splats import load_checkpoint
from wgs.gaussians.trainer import render_frame
from wgs.progress import log
from wgs.scene.dataset import composite, load_prepared
from wgs.shape.features import hull_channels
from wgs.shape.hull import visual_hull_grid
from wgs.threads import map_in_processes
from wgs.workspace import Workspace

SPARSITIES = (4, 6, 4, 3, 4, 5)  # cycled over objects: mostly 4 views, as the product default


def to_u8(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return (np.asarray(x, np.float32).clip(0, 1) * 255 + 0.5).astype(np.uint8)


def object_pairs(scene_dir: Path, work: Path, views: int, coarse_overrides: dict, seed: int = 0) -> dict:
    """prepare + coarse on `views` views of the scene, then G_c at every test pose -> arrays.
    One coarse model per object (the product's ensemble would cost ten for the same pairs)."""
    from wgs.stages.registry import run_stage
    from wgs.stages.stage import StageEnv

    ws = Workspace(work)
    t0 = time.perf_counter()
    env = StageEnv(torch.device("cpu"), seed, scene_dir=scene_dir)
    run_stage("prepare", ws, resolve("prepare", cli={"views": views}), env)
    run_stage("coarse", ws, resolve("coarse", cli={"ensemble": 1, **coarse_overrides}), env)
    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    splats, _ = load_checkpoint(ws.output("coarse", "model"), scene.norm)
    bg = torch.ones(3)
    centres = torch.stack([f.center for f in scene.train])
    grid = visual_hull_grid(scene.train, resolution=96, tolerate=0)
    out: dict[str, list] = {
        "render": [],
        "ref": [],
        "render_alpha": [],
        "ref_alpha": [],
        "distance": [],
        "hull": [],
        "hull_depth": [],
    }
    for f in scene.test:
        rgb, alpha = render_frame(splats, f, torch.device("cpu"), bg)
        hull, hull_depth = hull_channels(grid, f)
        out["hull"].append(to_u8(hull))
        out["hull_depth"].append(hull_depth.numpy().astype(np.float16))
        out["render"].append(to_u8(rgb))
        out["render_alpha"].append(to_u8(alpha[..., 0]))
        out["ref"].append(to_u8(composite(f.pixels, f.mask, bg)))
        out["ref_alpha"].append(to_u8(f.mask if f.mask is not None else torch.ones(f.height, f.width)))
        out["distance"].append(float((centres - f.center).norm(dim=1).min()))
    arrays: dict[str, Any] = {k: np.stack(v) for k, v in out.items()}
    arrays["distance"] = arrays["distance"].astype(np.float32)
    arrays["seconds"] = np.float32(time.perf_counter() - t0)
    return arrays


def build_pairs(
    cache: Path,
    coarse_overrides: dict,
    limit: int | None = None,
    budget_s: float | None = None,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
) -> int:
    """Pairs for every rendered corpus object without them yet; stops after budget_s seconds.
    workers > 1: that many processes of one thread each, objects dealt out round-robin."""
    if workers > 1:
        return sum(in_processes(build_pairs, workers, cache, coarse_overrides, limit, budget_s))
    listed = json.loads((cache / "corpus.json").read_text())["objects"]  # interleaved over the sources
    t0 = time.perf_counter()
    made = 0
    for i, meta in enumerate(listed[:limit]):
        if i % shard[1] != shard[0]:
            continue
        meta_path = cache / "objects" / meta["name"] / "object.json"
        views = SPARSITIES[i % len(SPARSITIES)]
        out = cache / "pairs" / f"{meta['name']}_v{views}.npz"
        if out.is_file():
            continue
        if budget_s is not None and time.perf_counter() - t0 > budget_s:
            log(f"pairs: budget of {budget_s:.0f} s spent; rerun to continue")
            break
        make = partial(object_pairs, meta_path.parent, views=views, coarse_overrides=coarse_overrides)
        arrays = save_object_pairs(out, cache / "work" / meta["name"], meta, make)
        if arrays is None:
            continue
        made += 1
        log(f"pairs: {meta['name']} ({views} views) {float(arrays['seconds']):.0f} s")
    return made


def save_object_pairs(out: Path, work: Path, meta: dict, make) -> dict | None:
    """make(work) -> arrays, in the scratch folder `work` (removed after), saved to `out` atomically
    with the object's holdout flag; None, with one line, when it fails (one bad object must not stop
    a long build)."""
    shutil.rmtree(work, ignore_errors=True)
    try:
        arrays = make(work)
    except Exception as exc:
        log(f"pairs: skipped {meta['name']}: {type(exc).__name__}: {exc}")
        return None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays, holdout=np.bool_(meta.get("holdout", False)))
    tmp.replace(out)
    return arrays


def in_processes(fn, n: int, *args) -> list:
    """fn(*args, workers=1, shard=(k, n)) for k < n in n spawned one-thread processes."""
    out: list = [None] * n
    for k, res in map_in_processes(_shard, [(fn, args, k, n) for k in range(n)], n, quiet=False):
        out[k] = res
    return out


def _shard(fn, args, k: int, n: int):
    return fn(*args, workers=1, shard=(k, n))


__all__ = ["build_pairs", "object_pairs", "in_processes"]
