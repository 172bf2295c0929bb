"""D's objective and trainer, for the per-object stage and the prior alike.

Two objectives, named by where the noised input starts (`models.denoiser_meta.DenoiserMeta.start`).
A model trained from the clean crop learns to copy x_t at low noise and ignores the corrupted
control signal, which is why a from-scratch D repairs little; the prior trains from the render.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F

from ..models.denoiser_meta import DenoiserMeta
from ..models.ll_denoiser import LLDenoiser
from ..models.sampling import single_step
from ..models.scheduler import DDIMScheduler
from .loop import FitPlan, FitState, fit, scalar


def denoiser_loss(
    model: LLDenoiser,
    sched: DDIMScheduler,
    clean: torch.Tensor,
    bad: torch.Tensor,
    meta: DenoiserMeta,
    gen: torch.Generator,
    charbonnier: float = 0.0,
) -> torch.Tensor:
    """One batch of D's objective: clean / bad [B, 3, h, w] on the model's device. charbonnier > 0:
    a robust L1 with that epsilon (sharper than L2's regression to the mean), else the MSE."""
    device = clean.device
    t = torch.randint(meta.noise_levels, (clean.shape[0],), generator=gen).to(device)
    x = bad if meta.start == "corrupted" else clean
    noise = torch.randn(x.shape, generator=gen).to(device)
    pred = model(sched.add_noise(x, noise, t), t, bad)
    if charbonnier > 0:
        return ((pred - clean).pow(2) + charbonnier**2).sqrt().mean()
    return F.mse_loss(pred, clean)


@torch.no_grad()
def held_out_mse(
    model: LLDenoiser, sched: DDIMScheduler, meta: DenoiserMeta, clean: torch.Tensor, bad: torch.Tensor, chunk: int = 64
) -> float:
    """MSE of D's single-step repair of held-out pairs [N, 3, h, w] (model space)."""
    rep = torch.cat([single_step(model, sched, bad[i : i + chunk], meta.repair_t) for i in range(0, len(bad), chunk)])
    return float((rep - clean).pow(2).mean())


def psnr_model_space(mse: float) -> float:
    return 10 * math.log10(4.0 / max(mse, 1e-12))  # model space [-1, 1] spans 2


def train_denoiser(
    model: LLDenoiser,
    meta: DenoiserMeta,
    batch: Callable[[], tuple[torch.Tensor, torch.Tensor]],
    plan: FitPlan,
    gen: torch.Generator,
    opt: torch.optim.Optimizer,
    *,
    held: tuple[torch.Tensor, torch.Tensor] | None = None,
    charbonnier: float = 0.0,
    bar_is_start: bool = False,
    name: str = "D",
    **loop: Any,
) -> tuple[LLDenoiser, FitState]:
    """Train D on `batch()` -> (clean, bad) on the model's device, with `meta`'s objective.
    held: held-out (clean, bad) pairs scored by `held_out_mse` at each record (a corrupted-start D
    only). bar_is_start: the starting weights are the bar to beat (a prior being adapted).
    `loop` goes to `training.loop.fit` (checkpoint, on_record, after_step)."""
    sched = DDIMScheduler(meta.train_timesteps)
    evaluate = None
    bar = math.inf
    if held is not None:

        def evaluate(m: LLDenoiser) -> float:
            return held_out_mse(m, sched, meta, *held)

        if bar_is_start:
            model.eval()
            bar = evaluate(model)
    return fit(
        model,
        opt,
        lambda step: denoiser_loss(model, sched, *batch(), meta, gen, charbonnier),
        plan,
        name,
        gen=gen,
        evaluate=evaluate,
        monitor=scalar if held is not None else None,
        bar=bar,
        **loop,
    )
