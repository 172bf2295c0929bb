"""Stage 3: train the repair diffusion model D (LL subband, or RGB for the ablation) and the HF
U-Net U (early stopping), each saved as config.json + model.safetensors under `3_finetune/`."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from ..config import FinetuneConfig
from ..errors import InputError
from ..io import atomic_write_json, read_json
from ..io.exr import read_subbands
from ..metrics import psnr
from ..models.data import hwc, load_pairs, random_crops
from ..models.denoiser_meta import DenoiserMeta
from ..models.hf_unet import HFUNet, HFUNetConfig
from ..models.ll_denoiser import LLDenoiser, LLDenoiserConfig
from ..models.sampling import sdedit_repair, single_step
from ..models.scheduler import DDIMScheduler
from ..models.storage import load_model, save_model
from ..prior import WEIGHTS as PRIOR_WEIGHTS
from ..progress import progress_bar
from ..resume import Checkpointer, check_interrupt, deferred_stop
from ..threads import adapt as adapt_threads
from ..training.denoiser import train_denoiser
from ..training.hf import train_hf
from ..training.loop import FitPlan, FitState
from ..wavelet.haar import idwt2
from ..workspace import StageRun, Workspace
from . import StageEnv
from .shared import subband_file


def split_holdout(n: int, frac: float, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    perm = torch.randperm(n, generator=gen)
    k = min(n - 1, max(1, round(frac * n))) if n > 1 else 0
    return perm[k:], perm[:k]


def resumable(what: str, checkpoint: Checkpointer | None) -> dict[str, Any]:
    """The loop options that make a stage's training loop resumable and Ctrl-C safe."""
    return {"checkpoint": checkpoint,
            "after_step": lambda step, snapshot: check_interrupt(what, step, checkpoint, snapshot)}


def progress(prog, status: Callable[[FitState], str]) -> Callable[[FitState], None]:
    return lambda st: prog.update(0, completed=st.step, status=status(st))


def train_scratch_d(cfg: FinetuneConfig, clean: torch.Tensor, bad: torch.Tensor, device: torch.device,
                    gen: torch.Generator, checkpoint: Checkpointer | None = None
                    ) -> tuple[LLDenoiser, dict[str, Any], DenoiserMeta]:
    """D from scratch (plain denoising, `start = clean`) on random crops of (clean, corrupted) pairs
    [P, 3, h, w]; returns the EMA weights, the curve and D's metadata."""
    meta = DenoiserMeta(domain=cfg.domain, levels=cfg.levels, train_timesteps=cfg.train_timesteps)
    model = LLDenoiser(LLDenoiserConfig(3, cfg.d_channels)).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.d_lr, weight_decay=0.0)
    plan = FitPlan(cfg.d_steps, cfg.d_lr, eval_every=25, ema_decay=cfg.ema_decay)

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        adapt_threads()
        idx = torch.randint(clean.shape[0], (cfg.d_batch,), generator=gen)
        return tuple(t.to(device) for t in random_crops([clean, bad], idx, cfg.d_crop, gen))

    with progress_bar("finetune D", cfg.d_steps) as prog, deferred_stop():
        model, st = train_denoiser(model, meta, batch, plan, gen, opt, name="finetune D",
                                   on_record=progress(prog, lambda st: f"loss {st.curve['loss'][-1]:.4f}"),
                                   **resumable("finetune D", checkpoint))
    return model, st.summary(), meta


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


def train_hf_unet(cfg: FinetuneConfig, renders: torch.Tensor, refs: torch.Tensor, device: torch.device,
                  gen: torch.Generator, checkpoint: Checkpointer | None = None, init: HFUNet | None = None
                  ) -> tuple[HFUNet, dict[str, Any]]:
    """U on augmented crops of the training views (`training.hf`), early-stopped on held-out crops
    (a held-out view when there are 3 or more, else fixed crops). init: start from these weights
    (the prior's U), at a tenth of the learning rate. curve["beats_identity"] False tells the
    caller to leave U out: no better than no HF repair."""
    n = renders.shape[0]
    val_ids = torch.tensor([n - 1]) if n >= 3 else torch.arange(n)
    train_ids = torch.arange(n - 1) if n >= 3 else torch.arange(n)
    fixed = torch.Generator().manual_seed(1234)
    held = random_crops([renders, refs], val_ids.repeat(8), 2 * cfg.u_crop, fixed, align=2)
    model = (init if init is not None else HFUNet(HFUNetConfig(channels=cfg.u_channels))).to(device)
    lr = cfg.u_lr if init is None else cfg.u_lr * 0.1
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    plan = FitPlan(cfg.u_max_steps, lr, cfg.u_eval_every, max_norm=None, patience=cfg.u_patience, keep_best=True,
                   min_delta=1e-7)

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        adapt_threads()
        idx = train_ids[torch.randint(len(train_ids), (cfg.u_batch,), generator=gen)]
        return tuple(t.to(device) for t in random_crops([renders, refs], idx, 2 * cfg.u_crop, gen, align=2))

    with progress_bar("finetune U", cfg.u_max_steps) as prog, deferred_stop():
        model, st, identity = train_hf(model, batch, plan, gen, opt, tuple(t.to(device) for t in held),
                                       start_is_bar=True, name="finetune U",
                                       on_record=progress(prog, lambda st: f"val L1 {st.curve['val'][-1]:.5f}"),
                                       **resumable("finetune U", checkpoint))
    return model, {**st.summary(), "identity": identity, "beats_identity": st.best < identity}


def prior_folder(cfg: FinetuneConfig) -> Path | None:
    """Where the pretrained D and U come from: the shipped prior, a folder, or none (from scratch).
    Only the LL-domain embedded D at one Haar level has a prior."""
    if cfg.prior == "none" or cfg.domain != "wavelet" or cfg.levels != 1 or cfg.diffusion != "embedded":
        return None
    return PRIOR_WEIGHTS if cfg.prior == "builtin" else Path(cfg.prior)


def finetune_prior_d(cfg: FinetuneConfig, prior: Path, clean: torch.Tensor, bad: torch.Tensor,
                     held_clean: torch.Tensor, held_bad: torch.Tensor, device: torch.device, gen: torch.Generator
                     ) -> tuple[LLDenoiser, DenoiserMeta, dict[str, Any]]:
    """The prior's D adapted to this object's pairs with its own objective (from the noised
    render), early-stopped on the held-out pairs; the prior itself wins unless a step beats it."""
    model, d_cfg = load_model(prior / "D", device)
    meta = DenoiserMeta.from_config(d_cfg, prior / "D" / "config.json")
    if meta.start != "corrupted":
        raise InputError("not a repair prior (its config lacks start = corrupted and t_max)",
                         prior / "D" / "config.json")
    meta.prior = str(prior)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.prior_lr, weight_decay=0.0)
    plan = FitPlan(cfg.prior_steps, cfg.prior_lr, cfg.prior_eval_every, patience=cfg.prior_patience, keep_best=True)

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        adapt_threads()
        idx = torch.randint(clean.shape[0], (cfg.d_batch,), generator=gen)
        return tuple(t.to(device) for t in random_crops([clean, bad], idx, cfg.d_crop, gen))

    with progress_bar("finetune D (prior)", cfg.prior_steps) as prog:
        held = (held_clean.to(device), held_bad.to(device))
        model, st = train_denoiser(model, meta, batch, plan, gen, opt, held=held, bar_is_start=True, name="finetune D",
                                   on_record=progress(prog, lambda st: f"held-out MSE {st.curve['val'][-1]:.5f} "
                                                                       f"(prior {st.bar:.5f})"))
    return model, meta, st.summary()


def heldout_check(cfg: FinetuneConfig, model: LLDenoiser, meta: DenoiserMeta, clean: torch.Tensor,
                  bad: torch.Tensor, device: torch.device) -> dict[str, float]:
    """Error of held-out corrupted samples against the clean ones, before and after D's repair
    (the way `wgs repair` runs this D)."""
    sched = DDIMScheduler(meta.train_timesteps)
    with torch.no_grad():
        if meta.start == "corrupted":
            rep = single_step(model, sched, bad.to(device), meta.repair_t).cpu()
        else:
            rep = sdedit_repair(model, sched, bad.to(device), cfg.eval_strength, cfg.eval_steps,
                                torch.Generator().manual_seed(0)).cpu()
    scale = 2.0  # model space [-1, 1] spans a range of 2
    return {"num_samples": int(clean.shape[0]),
            "l1_before": float((bad - clean).abs().mean()), "l1_after": float((rep - clean).abs().mean()),
            "psnr_before": psnr(bad, clean, scale), "psnr_after": psnr(rep.clamp(-1, 1), clean, scale)}


def plot_curves(path, curves: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    d = curves["D"]
    if d["bar"] is not None:  # a fine-tuned prior: its held-out error, step 0 = the prior as shipped
        axes[0].plot([0] + d["step"], [d["bar"]] + d["val"], label="held-out")
        axes[0].set(title="D from the prior (held-out MSE)", xlabel="step")
    else:
        axes[0].plot(d["step"], d["loss"])
        axes[0].set(title="D (clean-image MSE)", xlabel="step", yscale="log")
    if "U" in curves:
        u = curves["U"]
        axes[1].plot(u["step"], u["loss"], label="train")
        axes[1].plot(u["step"], u["val"], label="held-out")
        axes[1].axhline(u["identity"], ls="--", c="grey", label="no repair")
        axes[1].set(title="U (HF L1)" if u.get("beats_identity", True) else "U (HF L1): left out", xlabel="step")
        axes[1].legend()
    else:
        axes[1].axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_finetune(ws: Workspace, cfg: FinetuneConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_stage("finetune", cfg, {"seed": env.seed}, force,
                        lambda run: finetune(run, ws, cfg, env.device, env.seed))


def finetune(run: StageRun, ws: Workspace, cfg: FinetuneConfig, device: torch.device, seed: int) -> str:
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    if cfg.levels < 1:
        raise InputError(f"levels must be >= 1, got {cfg.levels}")
    clean, bad, pairs = load_pairs(ws.output("mask_data", "index"), cfg.domain, cfg.levels)
    train_ids, held = split_holdout(clean.shape[0], cfg.holdout, gen)
    record = train_and_save(run, ws, cfg, clean, bad, train_ids, held, device, gen)
    run.record.update(record)
    held_txt = (f"; held-out L1 {record['heldout']['l1_before']:.4f} -> {record['heldout']['l1_after']:.4f}"
                if "heldout" in record else "")
    u_txt = ""
    if "u_seconds" in record:
        kept = "kept" if record["u_used"] else "left out: no better than no HF repair on held-out crops"
        u_txt = f"; U {record['u_seconds']:.0f} s, stopped at {record['u_stopped_at']}, {kept}"
    return f"finetune: D {record['d_seconds']:.0f} s{held_txt}{u_txt}"


def train_lora(run: StageRun, cfg: FinetuneConfig, clean, bad, device, gen) -> dict[str, Any]:
    """SD 1.5 + ControlNet-tile with LoRA on the pairs shown as images in [0, 1] (LL / 2 for J = 1)."""
    from ..models import controlnet_lora as cl

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
            prog.update(0, completed=step, status=f"loss {losses[-1]:.4f}")
    cl.save_lora(run.dir / "D_lora", pipe, {"sd_model": str(Path(cfg.sd_model).resolve()),
                                            "controlnet": str(Path(cfg.controlnet).resolve()),
                                            "rank": cfg.lora_rank, "domain": cfg.domain, "levels": cfg.levels})
    return {"lora_final_loss": losses[-1] if losses else None, "lora_steps": cfg.lora_steps}


def train_and_save(run: StageRun, ws: Workspace, cfg: FinetuneConfig, clean, bad, train_ids, held,
                   device: torch.device, gen: torch.Generator) -> dict[str, Any]:
    t0 = time.perf_counter()
    if cfg.diffusion == "controlnet":
        record: dict[str, Any] = {"domain": cfg.domain, "levels": cfg.levels, "diffusion": "controlnet",
                                  **train_lora(run, cfg, clean[train_ids], bad[train_ids], device, gen),
                                  "d_seconds": round(time.perf_counter() - t0, 2), "num_pairs": int(clean.shape[0])}
        curves: dict[str, Any] = {}
        return finish_with_u(run, ws, cfg, record, curves, device, gen)
    ids = held if len(held) else train_ids
    prior = prior_folder(cfg)
    if prior is not None:
        d_model, meta, d_curve = finetune_prior_d(cfg, prior, clean[train_ids], bad[train_ids], clean[ids],
                                                  bad[ids], device, gen)
    else:
        d_model, d_curve, meta = train_scratch_d(cfg, clean[train_ids], bad[train_ids], device, gen,
                                                 run.checkpointer("d"))
    d_seconds = time.perf_counter() - t0
    save_model(run.dir / "D", d_model, meta.to_config())
    record: dict[str, Any] = {"domain": cfg.domain, "levels": cfg.levels, "d_seconds": round(d_seconds, 2),
                              "d_final_loss": d_curve["loss"][-1] if d_curve["loss"] else None,
                              "num_pairs": int(clean.shape[0]), "prior": None if prior is None else str(prior),
                              "heldout": heldout_check(cfg, d_model, meta, clean[ids], bad[ids], device)}
    if prior is not None:
        record["d_stopped_at"] = d_curve["stopped_at"]
    curves: dict[str, Any] = {"D": d_curve}
    return finish_with_u(run, ws, cfg, record, curves, device, gen, prior)


def finish_with_u(run: StageRun, ws: Workspace, cfg: FinetuneConfig, record: dict[str, Any], curves: dict[str, Any],
                  device: torch.device, gen: torch.Generator, prior: Path | None = None) -> dict[str, Any]:
    if cfg.domain == "wavelet" and cfg.use_u:
        t1 = time.perf_counter()
        renders, refs, _ = load_hf_data(ws)
        init = load_model(prior / "U", device)[0] if prior is not None else None
        u_model, u_curve = train_hf_unet(cfg, renders, refs, device, gen, run.checkpointer("u"), init)
        record.update({"u_seconds": round(time.perf_counter() - t1, 2), "u_best_val": u_curve["best"],
                       "u_identity_val": u_curve["identity"], "u_stopped_at": u_curve["stopped_at"],
                       "u_used": u_curve["beats_identity"]})
        if u_curve["beats_identity"]:  # else the repair leaves HF as rendered: what this scene needs
            save_model(run.dir / "U", u_model)
        curves["U"] = u_curve
    atomic_write_json(run.path("curves.json"), curves)
    if "D" in curves:
        plot_curves(run.path("curves.png"), curves)
    return record
