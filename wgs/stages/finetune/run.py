"""Stage 3: train the repair diffusion model D (LL subband, or RGB for the ablation) and the HF
U-Net U (early stopping), each saved as config.json + model.safetensors under `3_finetune/`."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from ...errors import InputError
from ...io import atomic_write_json, read_json
from ...io.exr import read_subbands
from ...models.data import hwc, load_pairs, random_crops
from ...models.hf_unet import HFUNet
from ...models.storage import load_model_of, save_model
from ...progress import BAR, progress_bar
from ...training.per_object import (
    finetune_prior_d,
    heldout_check,
    plot_curves,
    split_holdout,
    train_hf_unet,
    train_scratch_d,
)
from ...wavelet.haar import idwt2
from ...weights import WEIGHTS as PRIOR_WEIGHTS
from ...workspace import StageRun, Workspace
from ..shared import subband_file
from ..stage import StageEnv
from .settings import FinetuneConfig


def load_hf_data(ws: Workspace) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Coarse renders and references of the training views as images [V, 3, H, W] (from their subbands)."""
    names = read_json(ws.output("mask_data", "index"))["hf_views"]
    renders, refs = [], []
    for name in names:
        imgs = []
        for kind in ("render", "ref"):
            b = read_subbands(subband_file(ws, kind, name))
            ll = hwc(b["LL"])[None]
            hi = [(hwc(b["LH"])[None], hwc(b["HL"])[None], hwc(b["HH"])[None])]
            imgs.append(idwt2(ll, hi)[0])
        renders.append(imgs[0])
        refs.append(imgs[1])
    return torch.stack(renders), torch.stack(refs), names


def prior_folder(cfg: FinetuneConfig) -> Path | None:
    """Where the pretrained D and U come from: the shipped prior, a folder, or none (from scratch).
    Only the LL-domain embedded D at one Haar level has a prior."""
    if cfg.prior == "none" or cfg.domain != "wavelet" or cfg.levels != 1 or cfg.diffusion != "embedded":
        return None
    return PRIOR_WEIGHTS if cfg.prior == "builtin" else Path(cfg.prior)


def run_finetune(ws: Workspace, cfg: FinetuneConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_staged(
        "finetune", cfg, {"seed": env.seed}, force, lambda run: finetune(run, ws, cfg, env.device, env.seed)
    )


def finetune(run: StageRun, ws: Workspace, cfg: FinetuneConfig, device: torch.device, seed: int) -> str:
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    if cfg.levels < 1:
        raise InputError(f"levels must be >= 1, got {cfg.levels}")
    clean, bad, pairs = load_pairs(ws.output("mask_data", "index"), cfg.domain, cfg.levels)
    train_ids, held = split_holdout(clean.shape[0], cfg.holdout, gen)
    record = train_and_save(run, ws, cfg, clean, bad, train_ids, held, device, gen)
    run.record.update(record)
    held_txt = (
        f"; held-out L1 {record['heldout']['l1_before']:.4f} -> {record['heldout']['l1_after']:.4f}"
        if "heldout" in record
        else ""
    )
    u_txt = ""
    if "u_seconds" in record:
        kept = "kept" if record["u_used"] else "left out: no better than no HF repair on held-out crops"
        u_txt = f"; U {record['u_seconds']:.0f} s, stopped at {record['u_stopped_at']}, {kept}"
    return f"finetune: D {record['d_seconds']:.0f} s{held_txt}{u_txt}"


def train_lora(run: StageRun, cfg: FinetuneConfig, clean, bad, device, gen) -> dict[str, Any]:
    """SD 1.5 + ControlNet-tile with LoRA on the pairs shown as images in [0, 1] (LL / 2 for J = 1)."""
    from ...models import controlnet_lora as cl

    if not cfg.sd_model or not cfg.controlnet:
        raise InputError("--diffusion controlnet needs --sd-model PATH and --controlnet PATH (local folders)")
    pipe = cl.load_pipeline(Path(cfg.sd_model), Path(cfg.controlnet), device)
    params = cl.add_lora(pipe, cfg.lora_rank)
    opt = torch.optim.AdamW(params, lr=cfg.lora_lr)
    size = max(8, min(cfg.lora_crop, clean.shape[-1], clean.shape[-2]) // 8 * 8)
    losses = []
    with progress_bar("finetune D (LoRA)", cfg.lora_steps) as prog:
        for step in range(1, cfg.lora_steps + 1):
            idx = torch.randint(clean.shape[0], (1,), generator=gen)
            c, b = random_crops([clean, bad], idx, size, gen)
            losses.append(cl.lora_step(pipe, params, opt, ((c + 1) / 2).to(device), ((b + 1) / 2).to(device), gen))
            prog.update(BAR, completed=step, status=f"loss {losses[-1]:.4f}")
    cl.save_lora(
        run.dir / "D_lora",
        pipe,
        {
            "sd_model": str(Path(cfg.sd_model).resolve()),
            "controlnet": str(Path(cfg.controlnet).resolve()),
            "rank": cfg.lora_rank,
            "domain": cfg.domain,
            "levels": cfg.levels,
        },
    )
    return {"lora_final_loss": losses[-1] if losses else None, "lora_steps": cfg.lora_steps}


def train_and_save(
    run: StageRun,
    ws: Workspace,
    cfg: FinetuneConfig,
    clean,
    bad,
    train_ids,
    held,
    device: torch.device,
    gen: torch.Generator,
) -> dict[str, Any]:
    t0 = time.perf_counter()
    record: dict[str, Any]
    if cfg.diffusion == "controlnet":
        record = {
            "domain": cfg.domain,
            "levels": cfg.levels,
            "diffusion": "controlnet",
            **train_lora(run, cfg, clean[train_ids], bad[train_ids], device, gen),
            "d_seconds": round(time.perf_counter() - t0, 2),
            "num_pairs": int(clean.shape[0]),
        }
        return finish_with_u(run, ws, cfg, record, {}, device, gen)
    ids = held if len(held) else train_ids
    prior = prior_folder(cfg)
    if prior is not None:
        d_model, meta, d_curve = finetune_prior_d(
            cfg, prior, clean[train_ids], bad[train_ids], clean[ids], bad[ids], device, gen
        )
    else:
        d_model, d_curve, meta = train_scratch_d(
            cfg, clean[train_ids], bad[train_ids], device, gen, run.checkpointer("d")
        )
    d_seconds = time.perf_counter() - t0
    save_model(run.dir / "D", d_model, meta.to_config())
    record = {
        "domain": cfg.domain,
        "levels": cfg.levels,
        "d_seconds": round(d_seconds, 2),
        "d_final_loss": d_curve["loss"][-1] if d_curve["loss"] else None,
        "num_pairs": int(clean.shape[0]),
        "prior": None if prior is None else str(prior),
        "heldout": heldout_check(cfg, d_model, meta, clean[ids], bad[ids], device),
    }
    if prior is not None:
        record["d_stopped_at"] = d_curve["stopped_at"]
    return finish_with_u(run, ws, cfg, record, {"D": d_curve}, device, gen, prior)


def finish_with_u(
    run: StageRun,
    ws: Workspace,
    cfg: FinetuneConfig,
    record: dict[str, Any],
    curves: dict[str, Any],
    device: torch.device,
    gen: torch.Generator,
    prior: Path | None = None,
) -> dict[str, Any]:
    if cfg.domain == "wavelet" and cfg.use_u:
        t1 = time.perf_counter()
        renders, refs, _ = load_hf_data(ws)
        init = load_model_of(prior / "U", HFUNet, device)[0] if prior is not None else None
        u_model, u_curve = train_hf_unet(cfg, renders, refs, device, gen, run.checkpointer("u"), init)
        record.update(
            {
                "u_seconds": round(time.perf_counter() - t1, 2),
                "u_best_val": u_curve["best"],
                "u_identity_val": u_curve["identity"],
                "u_stopped_at": u_curve["stopped_at"],
                "u_used": u_curve["beats_identity"],
            }
        )
        if u_curve["beats_identity"]:  # else the repair leaves HF as rendered: what this scene needs
            save_model(run.dir / "U", u_model)
        curves["U"] = u_curve
    atomic_write_json(run.path("curves.json"), curves)
    if "D" in curves:
        plot_curves(run.path("curves.png"), curves)
    return record


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_finetune"]
