"""U's objective and trainer, for the per-object stage and the prior alike: L1 between U's output
and the reference's HF subbands, on crops of (render, reference) image pairs, the best held-out
state kept. The bar is no repair at all (identity) or, when U starts from weights, the better of
that and the starting weights: a U that cannot beat it is left as it started."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from ..models.hf_unet import HFUNet
from ..wavelet.haar import dwt2, stack_highs
from .loop import FitPlan, FitState, fit, scalar


def hf_triplet(render: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images [B, 3, H, W] -> the render's HF [B, 9, h, w], its LL (U's context), the reference's HF."""
    ll_c, [h_c] = dwt2(render, 1)
    _, [h_r] = dwt2(ref, 1)
    return stack_highs(h_c), ll_c, stack_highs(h_r)


def identity_l1(render: torch.Tensor, ref: torch.Tensor) -> float:
    """The HF L1 of no repair at all: the bar U must beat."""
    hc, _, hr = hf_triplet(render, ref)
    return (hc - hr).abs().mean().item()


def hf_l1(model: HFUNet, render: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    hc, ll, hr = hf_triplet(render, ref)
    return (model(hc, ll) - hr).abs().mean()


def train_hf(
    model: HFUNet,
    batch: Callable[[], tuple[torch.Tensor, torch.Tensor]],
    plan: FitPlan,
    gen: torch.Generator,
    opt: torch.optim.Optimizer,
    held: tuple[torch.Tensor, torch.Tensor],
    *,
    start_is_bar: bool,
    name: str = "U",
    chunk: int = 64,
    **loop: Any,
) -> tuple[HFUNet, FitState, float]:
    """Train U on `batch()` -> (render, reference) crops; held: held-out (render, reference) crops.
    start_is_bar: the starting weights must be beaten too (U from the prior). Returns U (its best
    held-out state), the loop's state and the held-out L1 of no repair."""
    v_hc, v_ll, v_hr = hf_triplet(*held)
    identity = identity_l1(*held)

    @torch.no_grad()
    def held_out_l1(m: HFUNet) -> float:
        if len(v_hc) <= chunk:
            return (m(v_hc, v_ll) - v_hr).abs().mean().item()
        return (
            sum(
                (m(v_hc[i : i + chunk], v_ll[i : i + chunk]) - v_hr[i : i + chunk]).abs().sum().item()
                for i in range(0, len(v_hc), chunk)
            )
            / v_hr.numel()
        )

    bar = min(identity, held_out_l1(model)) if start_is_bar else identity
    model, st = fit(
        model,
        opt,
        lambda step: hf_l1(model, *batch()),
        plan,
        name,
        gen=gen,
        evaluate=held_out_l1,
        monitor=scalar,
        bar=bar,
        **loop,
    )
    return model, st, identity
