"""The per-object fine-tune of the repair networks (`wgs finetune`): D from scratch or from the
shipped prior (early-stopped on held-out pairs), U with early stopping against no repair, the
held-out check and the curves' plot. The stage (`stages/finetune`) reads the pairs and writes
the models; these take tensors and a `FinetuneConfig`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from ..errors import InputError
from ..metrics import psnr
from ..models.data import random_crops
from ..models.denoiser_meta import DenoiserMeta
from ..models.hf_unet import HFUNet, HFUNetConfig
from ..models.ll_denoiser import LLDenoiser, LLDenoiserConfig
from ..models.sampling import sdedit_repair, single_step
from ..models.scheduler import DDIMScheduler
from ..models.storage import load_model_of
from ..progress import BAR, progress_bar
from ..resume import Checkpointer, check_interrupt, deferred_stop
from ..stages.finetune.settings import FinetuneConfig
from ..threads import adapt as adapt_threads
from .denoiser import train_denoiser
from .hf import train_hf
from .loop import FitPlan, FitState


def split_holdout(n: int, frac: float, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    perm = torch.randperm(n, generator=gen)
    k = min(n - 1, max(1, round(frac * n))) if n > 1 else 0
    return perm[k:], perm[:k]


def resumable(what: str, checkpoint: Checkpointer | None) -> dict[str, Any]:
    """The loop options that make a stage's training loop resumable and Ctrl-C safe."""
    return {
        "checkpoint": checkpoint,
        "after_step": lambda step, snapshot: check_interrupt(what, step, checkpoint, snapshot),
    }


def progress(prog, status: Callable[[FitState], str]) -> Callable[[FitState], None]:
    return lambda st: prog.update(BAR, completed=st.step, status=status(st))


def d_batches(
    cfg: FinetuneConfig, clean: torch.Tensor, bad: torch.Tensor, device: torch.device, gen: torch.Generator
) -> Callable[[], tuple[torch.Tensor, torch.Tensor]]:
    """D's training batches: `cfg.d_batch` random (clean, corrupted) crops of `cfg.d_crop` px."""

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        adapt_threads()
        idx = torch.randint(clean.shape[0], (cfg.d_batch,), generator=gen)
        return crops_on(device, clean, bad, idx, cfg.d_crop, gen)

    return batch


def train_scratch_d(
    cfg: FinetuneConfig,
    clean: torch.Tensor,
    bad: torch.Tensor,
    device: torch.device,
    gen: torch.Generator,
    checkpoint: Checkpointer | None = None,
) -> tuple[LLDenoiser, dict[str, Any], DenoiserMeta]:
    """D from scratch (plain denoising, `start = clean`) on random crops of (clean, corrupted) pairs
    [P, 3, h, w]; returns the EMA weights, the curve and D's metadata."""
    meta = DenoiserMeta(domain=cfg.domain, levels=cfg.levels, train_timesteps=cfg.train_timesteps)
    model = LLDenoiser(LLDenoiserConfig(3, cfg.d_channels)).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.d_lr, weight_decay=0.0)
    plan = FitPlan(cfg.d_steps, cfg.d_lr, eval_every=25, ema_decay=cfg.ema_decay)

    batch = d_batches(cfg, clean, bad, device, gen)

    with progress_bar("finetune D", cfg.d_steps) as prog, deferred_stop():
        model, st = train_denoiser(
            model,
            meta,
            batch,
            plan,
            gen,
            opt,
            name="finetune D",
            on_record=progress(prog, lambda st: f"loss {st.curve['loss'][-1]:.4f}"),
            **resumable("finetune D", checkpoint),
        )
    return model, st.summary(), meta


def crops_on(
    device: torch.device,
    a: torch.Tensor,
    b: torch.Tensor,
    idx: torch.Tensor,
    size: int,
    gen: torch.Generator,
    align: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The same random crops of a and b [P, C, H, W] at images idx (`models.data.random_crops`), on `device`."""
    ca, cb = random_crops([a, b], idx, size, gen, align=align)
    return ca.to(device), cb.to(device)


def train_hf_unet(
    cfg: FinetuneConfig,
    renders: torch.Tensor,
    refs: torch.Tensor,
    device: torch.device,
    gen: torch.Generator,
    checkpoint: Checkpointer | None = None,
    init: HFUNet | None = None,
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
    plan = FitPlan(
        cfg.u_max_steps,
        lr,
        cfg.u_eval_every,
        max_norm=None,
        patience=cfg.u_patience,
        keep_best=True,
        min_delta=1e-7,
        min_gain=cfg.u_min_gain,
    )

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        adapt_threads()
        idx = train_ids[torch.randint(len(train_ids), (cfg.u_batch,), generator=gen)]
        return crops_on(device, renders, refs, idx, 2 * cfg.u_crop, gen, align=2)

    with progress_bar("finetune U", cfg.u_max_steps) as prog, deferred_stop():
        model, st, identity = train_hf(
            model,
            batch,
            plan,
            gen,
            opt,
            (held[0].to(device), held[1].to(device)),
            start_is_bar=True,
            name="finetune U",
            on_record=progress(prog, lambda st: f"val L1 {st.curve['val'][-1]:.5f}"),
            **resumable("finetune U", checkpoint),
        )
    return model, {**st.summary(), "identity": identity, "beats_identity": st.best < identity}


def finetune_prior_d(
    cfg: FinetuneConfig,
    prior: Path,
    clean: torch.Tensor,
    bad: torch.Tensor,
    held_clean: torch.Tensor,
    held_bad: torch.Tensor,
    device: torch.device,
    gen: torch.Generator,
) -> tuple[LLDenoiser, DenoiserMeta, dict[str, Any]]:
    """The prior's D adapted to this object's pairs with its own objective (from the noised
    render), early-stopped on the held-out pairs; the prior itself wins unless a step beats it."""
    model, d_cfg = load_model_of(prior / "D", LLDenoiser, device)
    meta = DenoiserMeta.from_config(d_cfg, prior / "D" / "config.json")
    if meta.start != "corrupted":
        raise InputError(
            "not a repair prior (its config lacks start = corrupted and t_max)", prior / "D" / "config.json"
        )
    meta.prior = str(prior)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.prior_lr, weight_decay=0.0)
    plan = FitPlan(
        cfg.prior_steps,
        cfg.prior_lr,
        cfg.prior_eval_every,
        patience=cfg.prior_patience,
        keep_best=True,
        min_gain=cfg.prior_min_gain,
    )

    batch = d_batches(cfg, clean, bad, device, gen)

    with progress_bar("finetune D (prior)", cfg.prior_steps) as prog:
        held = (held_clean.to(device), held_bad.to(device))
        model, st = train_denoiser(
            model,
            meta,
            batch,
            plan,
            gen,
            opt,
            held=held,
            bar_is_start=True,
            name="finetune D",
            on_record=progress(prog, lambda st: f"held-out MSE {st.curve['val'][-1]:.5f} (prior {st.bar:.5f})"),
        )
    return model, meta, st.summary()


def heldout_check(
    cfg: FinetuneConfig,
    model: LLDenoiser,
    meta: DenoiserMeta,
    clean: torch.Tensor,
    bad: torch.Tensor,
    device: torch.device,
) -> dict[str, float]:
    """Error of held-out corrupted samples against the clean ones, before and after D's repair
    (the way `wgs repair` runs this D)."""
    sched = DDIMScheduler(meta.train_timesteps)
    with torch.no_grad():
        if meta.start == "corrupted":
            rep = single_step(model, sched, bad.to(device), meta.repair_t).cpu()
        else:
            rep = sdedit_repair(
                model, sched, bad.to(device), cfg.eval_strength, cfg.eval_steps, torch.Generator().manual_seed(0)
            ).cpu()
    scale = 2.0  # model space [-1, 1] spans a range of 2
    return {
        "num_samples": int(clean.shape[0]),
        "l1_before": float((bad - clean).abs().mean()),
        "l1_after": float((rep - clean).abs().mean()),
        "psnr_before": psnr(bad, clean, scale),
        "psnr_after": psnr(rep.clamp(-1, 1), clean, scale),
    }


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
