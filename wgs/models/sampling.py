"""Repair by diffusion: SDEdit-style sampling with the conditional denoiser."""

from __future__ import annotations

import torch

from .scheduler import DDIMScheduler


@torch.no_grad()
def sdedit_repair(
    model: torch.nn.Module,
    scheduler: DDIMScheduler,
    corrupted: torch.Tensor,
    strength: float,
    steps: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Noise the corrupted images [B, C, H, W] (model space) to `strength` and denoise them with DDIM,
    conditioned on the corrupted images. strength 1 starts from pure noise."""
    timesteps = scheduler.set_timesteps(steps, strength)
    noise = torch.randn(corrupted.shape, generator=generator).to(corrupted)
    t0 = int(timesteps[0])
    x = scheduler.add_noise(corrupted, noise, torch.full((corrupted.shape[0],), t0))
    for t in timesteps.tolist():
        out = model(x, torch.full((x.shape[0],), t, device=x.device), corrupted)
        x = scheduler.step(out, t, x, prediction=getattr(model, "prediction", "v"))
    return x


def single_step(
    model: torch.nn.Module,
    scheduler: DDIMScheduler,
    corrupted: torch.Tensor,
    t: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Difix-style repair by a model trained from the render (`start: corrupted`): the render
    noised to level t (t = 0: the render itself, deterministic), one prediction of the clean sample."""
    x = corrupted
    if t > 0:
        noise = torch.randn(corrupted.shape, generator=generator).to(corrupted)
        x = scheduler.add_noise(corrupted, noise, torch.full((corrupted.shape[0],), t))
    return model(x, torch.full((x.shape[0],), t, device=x.device), corrupted)
