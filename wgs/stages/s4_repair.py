"""Stage 4: pseudo references. Render G_c at novel viewpoints (from the training cameras only),
Haar-DWT, D repairs the LL subband (SDEdit), U repairs the HF subbands, inverse DWT. With an
RGB-domain D (`wgs finetune --domain rgb`) D repairs the RGB render and U is not used."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..config import RepairConfig, as_dict
from ..gaussians.splats import load_checkpoint
from ..gaussians.trainer import render_frame
from ..models.data import from_model, to_model
from ..models.sampling import sdedit_repair
from ..models.scheduler import DDIMScheduler
from ..models.storage import load_model
from ..progress import log
from ..scene.dataset import load_prepared
from ..scene.images import write_png
from ..scene.orbit import novel_views
from ..wavelet.exr import write_subbands
from ..wavelet.haar import dwt2, idwt2, split_highs, stack_highs
from ..workspace import StageRun, Workspace, atomic_write_json
from .s1_coarse import CKPT, background_for

VIEWS = "views.json"


def chw_to_hwc(x: torch.Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).float().numpy()


RepairFn = Callable[[torch.Tensor], torch.Tensor]  # [B, 3, h, w] model space -> repaired, model space


def embedded_repairer(D: torch.nn.Module, cfg: RepairConfig, train_timesteps: int, gen: torch.Generator,
                      device: torch.device) -> RepairFn:
    sched = DDIMScheduler(train_timesteps)
    return lambda x: sdedit_repair(D, sched, x.to(device), cfg.strength, cfg.steps, gen).cpu()


def controlnet_repairer(pipe, cfg: RepairConfig, seed: int) -> RepairFn:
    """SD img2img + ControlNet on images in [0, 1], padded to a multiple of 8 and cropped back."""
    from ..models import controlnet_lora as cl
    from ..models.blocks import pad_to_multiple

    def fn(x: torch.Tensor) -> torch.Tensor:
        img, (h, w) = pad_to_multiple(((x + 1) / 2).clamp(0, 1), 8)
        out = cl.repair(pipe, img.to(pipe.device), cfg.strength, cfg.steps, seed)
        return out[..., :h, :w] * 2 - 1

    return fn


@torch.no_grad()
def repair_image(render: torch.Tensor, repair_fn: RepairFn, U: torch.nn.Module | None, domain: str,
                 device: torch.device, levels: int = 1
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """render [H, W, 3] -> pseudo reference [H, W, 3] and the corrupted / repaired subbands.

    wavelet: D repairs LL_J; the coarser HF levels are kept, LL_1 is rebuilt from them, and U
    repairs the finest HF level with LL_1 as context."""
    x = render.permute(2, 0, 1)[None].double()
    h, w = x.shape[-2:]
    if domain == "rgb":
        out = from_model(repair_fn(to_model(x.float(), "rgb")), "rgb").double()
        bands_in = {"RGB": chw_to_hwc(x)}
        bands_out = {"RGB": chw_to_hwc(out)}
    else:
        llJ, highs = dwt2(x, levels)
        llJ_fixed = from_model(repair_fn(to_model(llJ.float(), "wavelet", levels)), "wavelet", levels).double()
        size1 = tuple(highs[0][0].shape[-2:])
        ll1 = idwt2(llJ, highs[1:], size=size1) if levels > 1 else llJ
        ll1_fixed = idwt2(llJ_fixed, highs[1:], size=size1) if levels > 1 else llJ_fixed
        hf = highs[0]
        hf_fixed = hf
        if U is not None:
            hf_fixed = split_highs(U(stack_highs(hf).float().to(device), ll1.float().to(device)).cpu().double())
        out = idwt2(ll1_fixed, [hf_fixed], size=(h, w))
        names = ("LL", "LH", "HL", "HH")
        bands_in = dict(zip(names, map(chw_to_hwc, (ll1, *hf)), strict=True))
        bands_out = dict(zip(names, map(chw_to_hwc, (ll1_fixed, *hf_fixed)), strict=True))
    return out[0].permute(1, 2, 0).clamp(0, 1).float(), bands_in, bands_out


def contact_sheet(rows: list[tuple[torch.Tensor, torch.Tensor]]) -> np.ndarray:
    """One row per view: render | repaired."""
    return np.concatenate([np.concatenate([a.numpy(), b.numpy()], axis=1) for a, b in rows], axis=0)


def run_repair(ws: Workspace, cfg: RepairConfig, device: torch.device, seed: int, force: bool = False) -> bool:
    config = as_dict(cfg)
    with ws.lock():
        fp = ws.begin("repair", config, {"seed": seed}, force, requires=("finetune",))
        if fp is None:
            return False
        scene = load_prepared(ws)
        with ws.stage_run("repair", config, fp) as run:
            record = repair_views(run, ws, scene, cfg, device, seed)
            run.record.update(record)
    log(f"repair: {record['num_views']} pseudo references in {record['seconds']:.1f} s")
    return True


def repair_views(run: StageRun, ws: Workspace, scene, cfg: RepairConfig, device: torch.device, seed: int
                 ) -> dict[str, Any]:
    import time

    t0 = time.perf_counter()
    splats, _ = load_checkpoint(ws.stage_dir("coarse") / CKPT, scene.norm, device)
    gen = torch.Generator().manual_seed(seed)
    ft = ws.stage_dir("finetune")
    if (ft / "D_lora").is_dir():
        from ..models.controlnet_lora import load_lora

        pipe, d_cfg = load_lora(ft / "D_lora", device)
        repair_fn = controlnet_repairer(pipe, cfg, seed)
    else:
        D, d_cfg = load_model(ft / "D", device)
        repair_fn = embedded_repairer(D, cfg, d_cfg.get("train_timesteps", 1000), gen, device)
    domain = d_cfg.get("domain", "wavelet")
    u_dir = ft / "U"
    U = load_model(u_dir, device)[0] if (domain == "wavelet" and u_dir.is_dir()) else None
    n_pairs = max(1, len(scene.train))
    per_pair = max(1, round(cfg.views_per_train * len(scene.train) / n_pairs))
    views = novel_views(scene.train, per_pair, cfg.arc_min, cfg.arc_max, seed)
    bg = background_for(scene)
    listing, rows = [], []
    d_max = max(d for _, d in views)
    for frame, dist in views:
        render, _ = render_frame(splats, frame, device, bg)
        fixed, bands_in, bands_out = repair_image(render, repair_fn, U, domain, device, d_cfg.get("levels", 1))
        stem = frame.name.rsplit(".", 1)[0]
        write_subbands(run.path("corrupted", f"{stem}.exr"), bands_in)
        write_subbands(run.path("repaired", f"{stem}.exr"), bands_out)
        write_subbands(run.path("pseudo", f"{stem}.exr"), {"RGB": fixed.numpy()}, half=False)
        write_png(run.path("pseudo", frame.name), fixed.numpy())
        rows.append((render, fixed))
        listing.append({"name": frame.name, "K": frame.K.tolist(), "viewmat": frame.viewmat.tolist(),
                        "width": frame.width, "height": frame.height, "distance": dist,
                        "weight": min(1.0, 2.0 * dist / d_max) if d_max > 0 else 1.0})
    write_png(run.path("contact_sheet.png"), contact_sheet(rows))
    atomic_write_json(run.path(VIEWS), {"domain": domain, "used_u": U is not None, "views": listing})
    return {"num_views": len(listing), "domain": domain, "used_u": U is not None,
            "seconds": round(time.perf_counter() - t0, 2)}
