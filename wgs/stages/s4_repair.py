"""Stage 4: pseudo references. Render G_c at novel viewpoints (from the training cameras only),
Haar-DWT, D repairs the LL subband, U repairs the HF subbands, inverse DWT. With an RGB-domain D
(`wgs finetune --domain rgb`) D repairs the RGB render and U is not used. When the coarse stage
trained an ensemble, every member's render is repaired and the repairs are averaged."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..config import VIEWS, RepairConfig, as_dict
from ..io import atomic_write_json
from ..models.repair import load_repairer
from ..progress import log
from ..scene.dataset import load_prepared
from ..scene.images import write_png
from ..scene.orbit import novel_views, sphere_views
from ..wavelet.exr import write_subbands
from ..workspace import StageRun, Workspace
from .shared import background_for, coarse_members, ensemble_repair


def contact_sheet(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> np.ndarray:
    """One row per view: render | repaired."""
    return np.concatenate([np.concatenate([a.numpy(), b.numpy()], axis=1) for a, b in rows], axis=0)


def run_repair(ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int, force: bool = False) -> bool:
    config = as_dict(cfg)
    with ws.lock():
        fp = ws.begin("repair", config, {"seed": seed}, force, requires=("finetune",))
        if fp is None:
            return False
        scene = load_prepared(ws.stage_dir("scene"))
        with ws.stage_run("repair", config, fp) as run:
            record = repair_views(run, ws, scene, cfg, device, seed)
            run.record.update(record)
    log(f"repair: {record['num_views']} pseudo references in {record['seconds']:.1f} s")
    return True


def repair_views(run: StageRun, ws: Workspace, scene, cfg: RepairConfig, device: torch.device, seed: int
                 ) -> dict[str, Any]:
    import time

    t0 = time.perf_counter()
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
    return {"num_views": len(listing), "domain": domain, "used_u": U is not None, "ensemble": len(members),
            "seconds": round(time.perf_counter() - t0, 2)}
