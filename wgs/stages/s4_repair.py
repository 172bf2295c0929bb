"""Stage 4: pseudo references. Render G_c at novel viewpoints (from the training cameras only),
Haar-DWT, D repairs the LL subband, U repairs the HF subbands, inverse DWT. With an RGB-domain D
(`wgs finetune --domain rgb`) D repairs the RGB render and U is not used. When the coarse stage
trained an ensemble, every member's render is repaired and the repairs are averaged."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..config import VIEWS, RepairConfig
from ..io import atomic_write_json
from ..io.exr import write_subbands
from ..io.images import write_png
from ..models.repair import load_repairer
from ..scene.dataset import load_prepared
from ..scene.orbit import novel_views, sphere_views
from ..workspace import StageRun, Workspace
from .shared import background_for, coarse_members, ensemble_repair


def contact_sheet(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> np.ndarray:
    """One row per view: render | repaired."""
    return np.concatenate([np.concatenate([a.numpy(), b.numpy()], axis=1) for a, b in rows], axis=0)


def run_repair(ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int, force: bool = False) -> bool:
    return ws.run_stage("repair", cfg, {"seed": seed}, force, lambda run: repair_views(run, ws, cfg, device, seed))


def repair_views(run: StageRun, ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int) -> str:
    t0 = time.perf_counter()
    scene = load_prepared(ws.stage_dir("scene"))
    members = coarse_members(ws, scene, device)
    repairer = load_repairer(ws.stage_dir("finetune"), cfg, device, seed)
    domain, U = repairer.d_cfg.get("domain", "wavelet"), repairer.U
    if cfg.poses == "sphere":
        views = sphere_views(scene.train, cfg.num_views, cfg.band_below, cfg.band_above)
    else:
        n_pairs = max(1, len(scene.train))
        per_pair = max(1, round(cfg.views_per_train * len(scene.train) / n_pairs))
        views = novel_views(scene.train, per_pair, cfg.arc_min, cfg.arc_max, seed)
    bg = background_for(scene)
    listing, rows = [], []
    d_max = max(d for _, d in views)
    for frame, dist in views:
        render, fixed, bands_in, bands_out = ensemble_repair(members, frame, bg, repairer, device)
        stem = frame.name.rsplit(".", 1)[0]
        write_subbands(run.path("corrupted", f"{stem}.exr"), bands_in)
        write_subbands(run.path("repaired", f"{stem}.exr"), bands_out)
        write_subbands(run.path("pseudo", f"{stem}.exr"), {"RGB": fixed.numpy()}, half=False)
        write_png(run.path("pseudo", frame.name), fixed.numpy())
        rows.append((render, fixed))
        listing.append({"name": frame.name, **frame.to_json(), "distance": dist,
                        "weight": min(1.0, 2.0 * dist / d_max) if d_max > 0 else 1.0})
    write_png(run.path("contact_sheet.png"), contact_sheet(rows))
    atomic_write_json(run.path(VIEWS), {"domain": domain, "used_u": U is not None, "views": listing})
    seconds = time.perf_counter() - t0
    run.record.update({"num_views": len(listing), "domain": domain, "used_u": U is not None,
                       "ensemble": len(members), "seconds": round(seconds, 2)})
    return f"repair: {len(listing)} pseudo references in {seconds:.1f} s"
