"""Stage 1: coarse 3DGS `G_c` on the sparse training views, its renders and their Haar subbands;
with `ensemble` > 1 also that many - 1 more coarse models from other seeds (`members/`), whose
repaired renders the repair stage averages with G_c's."""

from __future__ import annotations

import torch

from ..config import CKPT, PLY, CoarseConfig
from ..curves import CURVE, test_probe, write_curve
from ..gaussians.splats import VIEWER_SH_DEGREE, Splats, export_ply, save_checkpoint, to_world
from ..gaussians.trainer import render_frame, train_gaussians
from ..io import atomic_write_json
from ..io.exr import write_subbands
from ..io.images import write_png
from ..metrics import psnr
from ..progress import log
from ..scene.dataset import PreparedScene, composite, load_prepared
from ..workspace import StageRun, Workspace
from .shared import background_for, initial_splats, member_checkpoint, subbands_hwc


def write_coarse_outputs(run: StageRun, scene: PreparedScene, splats: Splats, device: torch.device) -> dict:
    bg = background_for(scene)
    per_view = {}
    for f in scene.train:
        ref = composite(f.image, f.mask, bg)
        rgb, _ = render_frame(splats, f, device, bg)
        write_png(run.path("renders", f.name), rgb.numpy())
        stem = f.name.rsplit(".", 1)[0]
        write_subbands(run.path("subbands", "ref", f"{stem}.exr"), subbands_hwc(ref))
        write_subbands(run.path("subbands", "render", f"{stem}.exr"), subbands_hwc(rgb))
        per_view[f.name] = psnr(rgb, ref)
    return per_view


def run_coarse(ws: Workspace, cfg: CoarseConfig, device: torch.device, seed: int, force: bool = False) -> bool:
    return ws.run_stage("coarse", cfg, {"seed": seed}, force, lambda run: train_coarse(run, ws, cfg, device, seed))


def train_coarse(run: StageRun, ws: Workspace, cfg: CoarseConfig, device: torch.device, seed: int) -> str:
    scene = load_prepared(ws.stage_dir("scene"))
    torch.manual_seed(seed)
    splats = initial_splats(scene, cfg, seed)
    log(f"coarse: {splats['means'].shape[0]} initial Gaussians, {len(scene.train)} views, "
        f"{cfg.iterations} iterations on {device}")
    probe, probe_names = test_probe(ws, scene, cfg, background_for(scene), device)
    res = train_gaussians(splats, scene.train, cfg, device, extent=1.0, desc="coarse", seed=seed,
                          has_masks=scene.has_masks, checkpoint=run.checkpointer("gc"), probe=probe)
    if probe is not None:
        write_curve(run.path(CURVE), res, probe_names)
    save_checkpoint(run.path(CKPT), res.splats, scene.norm, res.iterations)
    n_ply = export_ply(run.path(PLY), to_world(res.splats, scene.norm), VIEWER_SH_DEGREE)
    per_view = write_coarse_outputs(run, scene, res.splats, device)
    atomic_write_json(run.path("train_psnr.json"), per_view)
    mean_psnr = sum(per_view.values()) / len(per_view)
    member_s = []
    for i in range(1, cfg.ensemble):
        m = train_gaussians(initial_splats(scene, cfg, seed + i), scene.train, cfg, device, extent=1.0,
                            desc=f"coarse member {i + 1}/{cfg.ensemble}", seed=seed + i,
                            has_masks=scene.has_masks, checkpoint=run.checkpointer(f"gc{i}"))
        save_checkpoint(run.path(member_checkpoint(i)), m.splats, scene.norm, m.iterations)
        member_s.append(round(m.seconds, 2))
    # train_seconds: G_c alone (what a plain 3DGS of this config costs); the members' beside it
    run.record.update({"num_gaussians": n_ply, "iterations": res.iterations,
                       "train_seconds": round(res.seconds, 2), "final_loss": res.losses[-1],
                       "train_psnr": round(mean_psnr, 3), "seed": seed, "device": str(device),
                       "ensemble": cfg.ensemble, "member_seconds": member_s})
    return (f"coarse: {n_ply} Gaussians, training-view PSNR {mean_psnr:.2f} dB, {res.seconds:.1f} s"
            + (f"; {cfg.ensemble - 1} more ensemble members in {sum(member_s):.1f} s" if member_s else ""))
