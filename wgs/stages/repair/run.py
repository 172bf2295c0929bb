"""Stage 4: pseudo references. Render G_c at novel viewpoints (from the training cameras only),
Haar-DWT, D repairs the LL subband, U repairs the HF subbands, inverse DWT. With an RGB-domain D
(`wgs finetune --domain rgb`) D repairs the RGB render and U is not used. When the coarse stage
trained an ensemble, every member's render is repaired and the repairs are averaged. Where the
scene has masks, the volume model V carves the visual hull from its whole shape, the silhouette
model S predicts the object's outline at each pseudo view, and the hull is carved again with those
outlines (`shape.carve`): the fine stage starts from it."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ...errors import InputError
from ...gaussians.trainer import render_frame
from ...io import atomic_write_json
from ...io.exr import write_subbands
from ...io.images import write_png
from ...masking import grow
from ...models.repair import load_repairer
from ...models.storage import load_model
from ...progress import log
from ...scene.dataset import load_prepared
from ...scene.orbit import novel_views, sphere_views
from ...shape.carve import carve, carve_with_volume, sure_background
from ...shape.features import hull_channels, predict_object, silhouette_inputs
from ...shape.hull import HullGrid, save_grid, silhouette, visual_hull_grid
from ...shape.own_shape import describe as describe_own_shape
from ...shape.own_shape import own_shape
from ...shape.scores import HULL_CUT_LIMIT, hull_cut
from ...weights import WEIGHTS_S, WEIGHTS_V
from ...workspace import StageRun, Workspace
from ..shared import background_for, coarse_members, ensemble_repair
from ..stage import StageEnv
from .settings import STAGE, RepairConfig


def contact_sheet(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> np.ndarray:
    """One row per view: render | repaired."""
    return np.concatenate([np.concatenate([a.numpy(), b.numpy()], axis=1) for a, b in rows], axis=0)


@dataclass
class ShapeModels:
    """The strict visual hull of the training masks with the models that carve it (either may be None):
    S, the object probability at a camera, and V, the probability per voxel."""

    grid: HullGrid
    silhouette_model: torch.nn.Module | None
    volume_model: torch.nn.Module | None

    def predict(self, camera, render: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """S's [H, W] object probability from G_c's render [H, W, 3] and opacity [H, W, 1] at `camera`."""
        assert self.silhouette_model is not None
        return predict_object(
            self.silhouette_model, silhouette_inputs(render, alpha[..., 0], *hull_channels(self.grid, camera))
        )


def model_folder(setting: str, builtin: Path) -> Path | None:
    """A carving model's folder: the shipped one (None when the package has none) or the given one."""
    if setting != "builtin":
        return Path(setting)
    return builtin if (builtin / "model.safetensors").is_file() else None


def carving_folders(cfg: RepairConfig) -> dict[str, Path | None]:
    """Where S and V come from when carving is on."""
    if not cfg.carve:
        return {"S": None, "V": None}
    return {"S": model_folder(cfg.silhouette_model, WEIGHTS_S), "V": model_folder(cfg.volume_model, WEIGHTS_V)}


def carving_fingerprint(cfg: RepairConfig) -> dict[str, str | None]:
    """S's and V's weights' hashes: a new model makes the repair stage stale."""
    out = {}
    for name, folder in carving_folders(cfg).items():
        weights = folder / "model.safetensors" if folder is not None else None
        out[name] = (
            hashlib.sha256(weights.read_bytes()).hexdigest()[:16] if weights is not None and weights.is_file() else None
        )
    return out


def shape_models(scene, cfg: RepairConfig, device: torch.device) -> ShapeModels | None:
    """The hull and the models that carve it, or None (with one line) where the scene does not need
    or allow shaping the hull."""
    own = cfg.shape_revolution or cfg.shape_smooth
    if not (cfg.carve or own):
        return None
    if not scene.has_masks:
        log("repair: no masks -> no visual hull, no carving")
        return None
    folders = carving_folders(cfg)
    if not own and all(f is None for f in folders.values()):
        log("repair: no shipped silhouette or volume model -> no carving")
        return None
    try:
        grid = visual_hull_grid(scene.train, cfg.hull_resolution, tolerate=0)
        cut = hull_cut(scene.photos, cfg.hull_resolution)
    except InputError:  # the training starts from the hull that tolerates one mask; carving needs them all
        log("repair: the training masks share no region (every mask agreeing) -> no carving")
        return None
    if cut > HULL_CUT_LIMIT:
        log(
            f"repair: the hull of the other photos leaves out {cut:.1%} of each photo's mask (a mask misses part of "
            f"the object, or the photos crop it) -> no carving, no silhouettes at the pseudo views"
        )
        return None
    models = {k: load_model(f, device)[0] if f is not None else None for k, f in folders.items()}
    return ShapeModels(grid, models["S"], models["V"])


def carve_hull(shape: ShapeModels, scene, cfg: RepairConfig, run: StageRun) -> HullGrid:
    """The strict hull shrunk by what the photos' masks allow (`shape.own_shape`), then carved by V
    where the object's own leave-one-out silhouettes back it (the records go to the stage's manifest)."""
    hull, frames = shape.grid, scene.train
    if cfg.shape_revolution or cfg.shape_smooth:
        hull, record = own_shape(hull, scene.photos, cfg)
        run.record["own_shape"] = record
        log(f"repair: {describe_own_shape(record)}")
    if shape.volume_model is not None:
        hull, record = carve_with_volume(shape.volume_model, frames, hull, cfg, cfg.hull_resolution)
        run.record["volume_carving"] = record
        if record["used"]:
            log(
                f"repair: V carved {record['carved'] - record['restored']} of the hull's {record['voxels']} voxels "
                f"({record['restored']} kept for the real masks)"
            )
        else:
            log(
                f"repair: V would lower this object's leave-one-out silhouette IoU ({record['leave_one_out_iou']:.3f}"
                f" -> {record['leave_one_out_iou_carved']:.3f}) -> V does not carve"
            )
    return hull


def grown_silhouette(grid: HullGrid, camera, px: int) -> torch.Tensor:
    """[H, W] bool: the grid's silhouette at `camera`, grown by px pixels."""
    return grow(silhouette(grid, camera)[0], px) > 0.5


def run_repair(ws: Workspace, cfg: RepairConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_staged(
        "repair",
        cfg,
        {"seed": env.seed, "carving_models": carving_fingerprint(cfg)},
        force,
        lambda run: repair_views(run, ws, cfg, env.device, env.seed),
    )


def repair_views(run: StageRun, ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int) -> str:
    t0 = time.perf_counter()
    scene = load_prepared(ws.output("prepare", "prepared"))
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
    shape = shape_models(scene, cfg, device)
    hull = carve_hull(shape, scene, cfg, run) if shape is not None else None
    use_s = shape is not None and shape.silhouette_model is not None
    listing, rows, probs = [], [], []
    d_max = max(d for _, d in views)
    for frame, dist in views:
        first, alpha = render_frame(members[0], frame, device, bg)
        render, fixed, bands_in, bands_out = ensemble_repair(members, frame, bg, repairer, device, first_render=first)
        stem = frame.name.rsplit(".", 1)[0]
        extra = {}
        if shape is not None and hull is not None:  # where the object may be: inside V's hull, but for what
            # S is sure is background
            may_be = grown_silhouette(hull, frame, cfg.dilate_px)
            if use_s:
                probs.append(shape.predict(frame, first, alpha))
                may_be &= ~sure_background(probs[-1], cfg)
            write_png(run.output("silhouettes", frame.name), may_be.float()[..., None].expand(-1, -1, 3).numpy())
            extra["silhouette"] = f"{STAGE.outputs['silhouettes']}/{frame.name}"
        write_subbands(run.path("corrupted", f"{stem}.exr"), bands_in)
        write_subbands(run.path("repaired", f"{stem}.exr"), bands_out)
        write_subbands(run.output("pseudo", f"{stem}.exr"), {"RGB": fixed.numpy()}, half=False)
        write_png(run.output("pseudo", frame.name), fixed.numpy())
        rows.append((render, fixed))
        listing.append(
            {
                "name": frame.name,
                **frame.to_json(),
                "distance": dist,
                "weight": min(1.0, 2.0 * dist / d_max) if d_max > 0 else 1.0,
                **extra,
            }
        )
    if use_s and shape is not None and hull is not None:  # S also at views over the whole sphere: the band
        # leaves the poles uncarved
        around = [f for f, _ in sphere_views(scene.train, cfg.carve_views, 180.0, 180.0)]
        probs += [shape.predict(f, *render_frame(members[0], f, device, bg)) for f in around]
        hull, counts = carve(hull, [f for f, _ in views] + around, probs, scene.train, cfg)
        run.record["carving"] = counts
        log(
            f"repair: S carved {counts['carved'] - counts['restored']} of the hull's {counts['voxels']} voxels "
            f"({counts['restored']} kept for the real masks)"
        )
    if hull is not None:
        save_grid(run.output("carved_hull"), hull)
    write_png(run.output("contact_sheet"), contact_sheet(rows))
    atomic_write_json(run.output("views"), {"domain": domain, "used_u": U is not None, "views": listing})
    seconds = time.perf_counter() - t0
    run.record.update(
        {
            "num_views": len(listing),
            "domain": domain,
            "used_u": U is not None,
            "ensemble": len(members),
            "seconds": round(seconds, 2),
        }
    )
    return f"repair: {len(listing)} pseudo references in {seconds:.1f} s"


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_repair", "shape_models", "ShapeModels"]
