"""One optimisation step of the repair networks (shared by the per-object and the prior training)."""

from __future__ import annotations

import math

import torch

from ..errors import WgsError


def clipped_step(
    opt: torch.optim.Optimizer,
    model: torch.nn.Module,
    loss: torch.Tensor,
    where: str,
    step: int,
    ema: torch.nn.Module | None = None,
    ema_decay: float = 0.0,
    max_norm: float | None = 1.0,
) -> float:
    """Backward, gradient-norm clip (unless max_norm is None), step, optional EMA of the weights; a
    non-finite loss stops the loop with one line naming `where` and the step. Returns the loss value."""
    value = loss.item()
    if not math.isfinite(value):
        raise WgsError(f"{where}: the training loss became non-finite at step {step}; nothing was saved")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if max_norm is not None:
        torch.nn.utils.clip_grad_norm_(model.parameters(), max_norm)
    opt.step()
    if ema is not None:
        with torch.no_grad():
            for pe, pm in zip(ema.parameters(), model.parameters(), strict=True):
                pe.lerp_(pm, 1 - ema_decay)
    return value
