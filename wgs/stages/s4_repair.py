"""Stage 4: pseudo references. Render G_c at novel viewpoints (from the training cameras only),
Haar-DWT, D repairs the LL subband, U repairs the HF subbands, inverse DWT. With an RGB-domain D
(`wgs finetune --domain rgb`) D repairs the RGB render and U is not used. When the coarse stage
trained an ensemble, every member's render is repaired and the repairs are averaged. Where the
scene has masks, the silhouette model S predicts the object's outline at each pseudo view, and
the visual hull is carved with those outlines (`shape.carve`): the fine stage starts from it."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..config import OUTPUTS, RepairConfig
from ..errors import InputError
from ..gaussians.trainer import render_frame
from ..io import atomic_write_json
from ..io.exr import write_subbands
from ..io.images import write_png
from ..models.repair import load_repairer
from ..models.storage import load_model
from ..prior import WEIGHTS_S
from ..progress import log
from ..scene.dataset import load_prepared
from ..scene.orbit import novel_views, sphere_views
from ..shape.carve import carve, sure_background
from ..shape.features import hull_channels, predict_object, silhouette_inputs
from ..shape.hull import HullGrid, save_grid, visual_hull_grid
from ..workspace import StageRun, Workspace
from . import StageEnv
from .shared import background_for, coarse_members, ensemble_repair


def contact_sheet(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> np.ndarray:
    """One row per view: render | repaired."""
    return np.concatenate([np.concatenate([a.numpy(), b.numpy()], axis=1) for a, b in rows], axis=0)


@dataclass
class SilhouettePredictor:
    """S with the strict visual hull of the training masks: the object probability at any camera."""

    model: torch.nn.Module
    grid: HullGrid
    device: torch.device

    def predict(self, camera, render: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """[H, W] object probability from G_c's render [H, W, 3] and opacity [H, W, 1] at `camera`."""
        return predict_object(self.model, silhouette_inputs(render, alpha[..., 0],
                                                            *hull_channels(self.grid, camera)))


def silhouette_folder(cfg: RepairConfig) -> Path | None:
    """Where S comes from when carving is on: the shipped S (None when the package has none) or a folder."""
    if not cfg.carve:
        return None
    if cfg.silhouette_model != "builtin":
        return Path(cfg.silhouette_model)
    return WEIGHTS_S if (WEIGHTS_S / "model.safetensors").is_file() else None


def silhouette_fingerprint(cfg: RepairConfig) -> str | None:
    """S's weights' hash: a new S makes the repair stage stale."""
    folder = silhouette_folder(cfg)
    weights = folder / "model.safetensors" if folder is not None else None
    return hashlib.sha256(weights.read_bytes()).hexdigest()[:16] if weights is not None and weights.is_file() else None


def silhouette_predictor(scene, cfg: RepairConfig, device: torch.device) -> SilhouettePredictor | None:
    """S and the hull it carves, or None (with one line) where the scene does not need or allow carving."""
    if not cfg.carve:
        return None
    if not scene.has_masks:
        log("repair: no masks -> no visual hull, no carving")
        return None
    folder = silhouette_folder(cfg)
    if folder is None:
        log("repair: no shipped silhouette model S -> no carving")
        return None
    try:
        grid, _ = visual_hull_grid(scene.train, cfg.hull_resolution, tolerate=0)
    except InputError:  # the training starts from the hull that tolerates one mask; carving needs them all
        log("repair: the training masks share no region (every mask agreeing) -> no carving")
        return None
    model, _ = load_model(folder, device)
    return SilhouettePredictor(model, grid, device)


def run_repair(ws: Workspace, cfg: RepairConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_stage("repair", cfg, {"seed": env.seed, "silhouette_model": silhouette_fingerprint(cfg)}, force,
                        lambda run: repair_views(run, ws, cfg, env.device, env.seed))


def repair_views(run: StageRun, ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int) -> str:
    t0 = time.perf_counter()
    scene = load_prepared(ws.output("scene", "prepared"))
    members = coarse_members(ws, scene, device)
    repairer = load_repairer(ws.output("finetune", "models"), cfg, device, seed)
    domain, U = repairer.meta.domain, repairer.U
    if cfg.poses == "sphere":
        views = sphere_views(scene.train, cfg.num_views, cfg.band_below, cfg.band_above)
    else:
        n_pairs = max(1, len(scene.train))
        per_pair = max(1, round(cfg.views_per_train * len(scene.train) / n_pairs))
        views = novel_views(scene.train, per_pair, cfg.arc_min, cfg.arc_max, seed)
    bg = background_for(scene)
    shape = silhouette_predictor(scene, cfg, device)
    listing, rows, probs = [], [], []
    d_max = max(d for _, d in views)
    for frame, dist in views:
        first, alpha = render_frame(members[0], frame, device, bg)
        render, fixed, bands_in, bands_out = ensemble_repair(members, frame, bg, repairer, device, first_render=first)
        stem = frame.name.rsplit(".", 1)[0]
        extra = {}
        if shape is not None:  # where the object may be: all but what S is sure is background
            probs.append(shape.predict(frame, first, alpha))
            may_be = (~sure_background(probs[-1], cfg)).float()
            write_png(run.output("silhouettes", frame.name), may_be[..., None].expand(-1, -1, 3).numpy())
            extra["silhouette"] = f"{OUTPUTS['repair']['silhouettes']}/{frame.name}"
        write_subbands(run.path("corrupted", f"{stem}.exr"), bands_in)
        write_subbands(run.path("repaired", f"{stem}.exr"), bands_out)
        write_subbands(run.output("pseudo", f"{stem}.exr"), {"RGB": fixed.numpy()}, half=False)
        write_png(run.output("pseudo", frame.name), fixed.numpy())
        rows.append((render, fixed))
        listing.append({"name": frame.name, **frame.to_json(), "distance": dist,
                        "weight": min(1.0, 2.0 * dist / d_max) if d_max > 0 else 1.0, **extra})
    if shape is not None:  # S also at views over the whole sphere: the band leaves the poles uncarved
        around = [f for f, _ in sphere_views(scene.train, cfg.carve_views, 180.0, 180.0)]
        probs += [shape.predict(f, *render_frame(members[0], f, device, bg)) for f in around]
        carved, counts = carve(shape.grid, [f for f, _ in views] + around, probs, scene.train, cfg)
        save_grid(run.output("carved_hull"), carved)
        run.record["carving"] = counts
        log(f"repair: S carved {counts['carved'] - counts['restored']} of the hull's {counts['voxels']} voxels "
            f"({counts['restored']} kept for the real masks)")
    write_png(run.output("contact_sheet"), contact_sheet(rows))
    atomic_write_json(run.output("views"), {"domain": domain, "used_u": U is not None, "views": listing})
    seconds = time.perf_counter() - t0
    run.record.update({"num_views": len(listing), "domain": domain, "used_u": U is not None,
                       "ensemble": len(members), "seconds": round(seconds, 2)})
    return f"repair: {len(listing)} pseudo references in {seconds:.1f} s"
