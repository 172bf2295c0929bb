"""Helpers for the experiment scripts (not part of wgs)."""

import dataclasses
from pathlib import Path

import torch

from wgs.config import resolve
from wgs.gaussians.splats import save_checkpoint
from wgs.gaussians.trainer import train_gaussians
from wgs.metrics import psnr
from wgs.scene.dataset import composite, load_prepared
from wgs.stages.shared import ensemble_repair, initial_splats


def train_subset(
    scene_dir: str, keep: list[int], seed: int, out: str, overrides: dict | None = None, hull_all: bool = False
) -> str:
    """One coarse model on the training views `keep` (visual hull from those views, or all: hull_all)."""
    scene = load_prepared(Path(scene_dir))
    sub = dataclasses.replace(scene, train=[scene.train[i] for i in keep])
    cfg = resolve("coarse", cli={"ensemble": 1, **(overrides or {})})
    torch.manual_seed(seed)
    init = initial_splats(scene if hull_all else sub, cfg, seed)
    res = train_gaussians(init, sub.train, cfg, torch.device("cpu"), extent=1.0, seed=seed, has_masks=sub.has_masks)
    save_checkpoint(Path(out), res.splats, scene.norm, res.iterations)
    return out


def score_refs(members, frames, bg, repairer, device=torch.device("cpu")) -> float:
    """Mean PSNR of the ensemble's pseudo references at `frames` against their ground truth."""
    vals = []
    for f in frames:
        _, ref, _, _ = ensemble_repair(members, f, bg, repairer, device)
        vals.append(psnr(ref.clamp(0, 1), composite(f.image, f.mask, bg)))
    return sum(vals) / len(vals)
