"""What the stages share: the background renders are composited on, the initial Gaussians, the
subbands of a render, the ensemble's members and their repair. Stages import this module and the
layers below it, never each other."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from ..cost import time_boxed
from ..errors import InputError
from ..gaussians.init import hull_points, knn_mean_distance, random_init, visual_hull
from ..gaussians.splats import Splats, create_splats, load_checkpoint
from ..gaussians.trainer import TrainConfig, render_frame
from ..models.repair import Repairer, load_repairer, repair_image, symmetrized
from ..progress import log
from ..scene.dataset import Frame, PreparedScene
from ..shape.hull import HullGrid
from ..wavelet.haar import dwt2
from .baseline.settings import BaselineConfig
from .coarse.settings import CoarseConfig
from .registry import METHOD, STAGE


def initial_splats(scene: PreparedScene, cfg: TrainConfig, seed: int, hull: HullGrid | None = None) -> Splats:
    """Visual hull of the masks when the scene has them (or the given, carved, hull), else random
    points in the object region."""
    gen = torch.Generator().manual_seed(seed)
    if hull is not None:
        pts, cols = hull_points(hull, scene.train, cfg.init_points, gen)
    elif scene.has_masks:
        try:
            pts, cols = visual_hull(scene.train, cfg.hull_resolution, 1.0, cfg.init_points, generator=gen)
        except InputError as exc:  # name the scene the user gave, whose masks and poses are at fault
            raise InputError(exc.message, scene.info.get("source")) from None
    else:
        log("no masks -> no visual hull, no mask loss, no random background (random init)")
        pts, cols = random_init(cfg.init_points, generator=gen)
    scales = knn_mean_distance(pts, 3).clamp(1e-4, 0.05)
    return create_splats(pts, cols, scales, cfg.sh_degree)


def plain_3dgs_config(
    coarse: CoarseConfig, budget_s: float, coarse_train_s: float, headroom: float = BaselineConfig.headroom
) -> CoarseConfig:
    """Plain 3DGS for a training-time budget (what the time would buy without the repair): the
    coarse stage's settings for one model, time-boxed (`config.time_boxed`) from G_c's own rate."""
    return dataclasses.replace(time_boxed(coarse, budget_s, coarse_train_s, headroom), ensemble=1)


def recorded_config(ws, stage: str) -> Any:
    """The settings `stage` last ran with, from its manifest (defaults where it has none)."""
    cls = STAGE[stage].settings
    recorded = (ws.manifest(stage) or {}).get("config") or {}
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in recorded.items() if k in names})


def background_for(scene: PreparedScene) -> torch.Tensor:
    """Renders and references on disk are composited on white for masked objects (the datasets' way)."""
    return torch.ones(3) if scene.has_masks else torch.zeros(3)


def subbands_hwc(img: torch.Tensor) -> dict[str, np.ndarray]:
    """[H, W, 3] -> {"LL","LH","HL","HH": [h, w, 3] numpy} with one Haar level."""
    ll, [(lh, hl, hh)] = dwt2(img.permute(2, 0, 1)[None].double(), 1)
    return {n: b[0].permute(1, 2, 0).float().numpy() for n, b in (("LL", ll), ("LH", lh), ("HL", hl), ("HH", hh))}


def stage_times(ws) -> list[dict[str, Any]]:
    """Wall time, cumulative wall time, peak memory, the run's estimate (`Workspace.run_record`,
    None where it made none), its estimate after the coarse stage's pilots (`estimate_after_pilots`)
    and the stage's wall time after them (the coarse stage's less its pilots'), and the iterations
    and where the stopping rule ended them, of each method stage that ran, in order."""
    rows, cum = [], 0.0
    record = ws.run_record()
    estimate = record.get("estimate") or {}
    after_pilots = record.get("estimate_after_pilots") or {}
    for st in METHOD:
        m = ws.manifest(st)
        if m is None:
            continue
        cum += m.get("wall_time_s", 0.0)
        pilots_s = (m.get("stopping") or {}).get("pilots_s", 0.0)
        rows.append(
            {
                "stage": st,
                "wall_time_s": m.get("wall_time_s", 0.0),
                "cumulative_s": round(cum, 2),
                "peak_memory_mb": m.get("peak_memory_mb"),
                "estimate_s": estimate.get(st),
                "estimate_after_pilots_s": after_pilots.get(st),
                "after_pilots_s": max(m.get("wall_time_s", 0.0) - pilots_s, 0.0),
                "iterations": m.get("iterations"),
                "stopping": m.get("stopping"),  # where the held-out rule stopped it (None: all its iterations)
            }
        )
    return rows


def subband_file(ws, kind: str, view: str):
    """The coarse stage's Haar subbands of training view `view`: kind "render" (G_c) or "ref" (the photo)."""
    return ws.output("coarse", "subbands", kind, f"{view.rsplit('.', 1)[0]}.exr")


def newest_model(ws) -> str:
    """The stage whose model a command shows by default: fine when it has run, else coarse."""
    return "fine" if ws.manifest("fine") is not None else "coarse"


def member_file(i: int) -> str:
    """File of ensemble member i (>= 1) in the coarse stage's `members` output; member 0 is G_c (its `model`)."""
    return f"ckpt_{i}.pt"


def coarse_members(ws, scene: PreparedScene, device: torch.device) -> list[Splats]:
    """G_c and the coarse stage's other ensemble members (as many as it trained)."""
    n = int((ws.manifest("coarse") or {}).get("ensemble", 1))
    return [
        load_checkpoint(
            ws.output("coarse", "model") if i == 0 else ws.output("coarse", "members", member_file(i)),
            scene.norm,
            device,
        )[0]
        for i in range(n)
    ]


def workspace_repairer(ws, device: torch.device, seed: int) -> Repairer:
    """D and U from the finetune stage, with the repair stage's settings."""
    return load_repairer(ws.output("finetune", "models"), recorded_config(ws, "repair"), device, seed)


@torch.no_grad()
def ensemble_repair(
    members: list[Splats],
    frame: Frame,
    background: torch.Tensor,
    repairer: Repairer,
    device: torch.device,
    first_render: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, dict, dict]:
    """The pseudo reference at one camera: every member's render repaired by D and U, averaged.

    Member k's D sees its render under its own symmetries of the square (k * n .. k * n + n - 1 for
    n = repairer.symmetries): D's errors then differ between members too (lego, 4 views, 40 test
    poses, 4 models: 20.57 dB with D on every render as it is, 20.63 with a flip or transpose each).
    `first_render`: the first member's render when the caller has it. Returns that render [H, W, 3],
    the reference [H, W, 3], and the corrupted
    (first render) and repaired (reference) subbands as `repair_image` names them."""
    domain, levels = repairer.meta.domain, repairer.meta.levels
    n = repairer.symmetries
    fixed = []
    for k, splats in enumerate(members):
        render = (
            first_render if k == 0 and first_render is not None else render_frame(splats, frame, device, background)[0]
        )
        fn = symmetrized(repairer.fn, n, first=k * n)
        out, bands_in_k, bands_out = repair_image(render, fn, repairer.U, domain, device, levels)
        if k == 0:
            first, bands_in = render, bands_in_k
        fixed.append(out)
    if len(fixed) == 1:
        return first, fixed[0], bands_in, bands_out
    mean = torch.stack(fixed).mean(0)
    return first, mean, bands_in, (subbands_hwc(mean) if domain == "wavelet" else {"RGB": mean.numpy()})
