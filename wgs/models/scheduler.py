"""DDIM noise scheduler with v- or sample-prediction and zero terminal SNR (diffusers-style API).

Betas follow the "scaled linear" schedule of Stable Diffusion, rescaled so that alpha_bar(T) = 0
(Lin et al., "Common Diffusion Noise Schedules and Sample Steps are Flawed"): the model then
sees pure noise at t = T. With v-prediction x0 = sqrt(ab)·x_t - sqrt(1-ab)·v stays finite at
alpha_bar = 0, where epsilon-prediction would divide by zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class DDIMScheduler:
    num_train_timesteps: int = 1000
    beta_start: float = 0.00085
    beta_end: float = 0.012

    def __post_init__(self) -> None:
        betas = (
            torch.linspace(self.beta_start**0.5, self.beta_end**0.5, self.num_train_timesteps, dtype=torch.float64) ** 2
        )
        ab = torch.cumprod(1 - betas, 0)
        # zero terminal SNR: shift and scale sqrt(alpha_bar) so its last value is exactly 0
        s = ab.sqrt()
        s0, sT = s[0].clone(), s[-1].clone()
        s = (s - sT) * s0 / (s0 - sT)
        self.alphas_cumprod = s**2  # [T], float64
        self.timesteps = torch.arange(self.num_train_timesteps - 1, -1, -1)

    def _ab(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        ab = self.alphas_cumprod.to(like.device)[t.to(like.device).long()].to(like.dtype)
        return ab.reshape(-1, *([1] * (like.dim() - 1)))

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) noise; x0, noise [B, ...], t [B] int."""
        ab = self._ab(t, x0)
        return ab.sqrt() * x0 + (1 - ab).sqrt() * noise

    def get_velocity(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The v-prediction target: v = sqrt(ab) noise - sqrt(1 - ab) x0."""
        ab = self._ab(t, x0)
        return ab.sqrt() * noise - (1 - ab).sqrt() * x0

    def set_timesteps(self, num_inference_steps: int, strength: float = 1.0) -> torch.Tensor:
        """Descending timesteps for sampling; strength < 1 starts part-way (SDEdit)."""
        if num_inference_steps < 1:
            raise ValueError("num_inference_steps must be >= 1")
        if not 0 < strength <= 1:
            raise ValueError(f"strength must be in (0, 1], got {strength}")
        t_start = round(strength * (self.num_train_timesteps - 1))
        ts = torch.linspace(t_start, 0, num_inference_steps + 1).round().long()
        self.timesteps = torch.unique_consecutive(ts)[:-1] if num_inference_steps > 1 else ts[:1]
        return self.timesteps

    def predict_x0(self, v: torch.Tensor, t: int, sample: torch.Tensor) -> torch.Tensor:
        ab = self._ab(torch.tensor([t]), sample)
        return ab.sqrt() * sample - (1 - ab).sqrt() * v

    def step(
        self, model_output: torch.Tensor, t: int, sample: torch.Tensor, prev_t: int | None = None, prediction: str = "v"
    ) -> torch.Tensor:
        """One deterministic DDIM step (eta = 0) from t to prev_t (default: the next scheduled step;
        -1 returns the predicted clean sample). prediction: "v" or "sample" (the model predicts x0)."""
        if prev_t is None:
            later = self.timesteps[self.timesteps < t]
            prev_t = int(later[0]) if len(later) else -1
        ab_t = self._ab(torch.tensor([t]), sample)
        if prediction == "v":
            x0 = ab_t.sqrt() * sample - (1 - ab_t).sqrt() * model_output
            eps = (1 - ab_t).sqrt() * sample + ab_t.sqrt() * model_output
        elif prediction == "sample":
            x0 = model_output
            # 1 - ab_t >= beta_0 > 0 for every t, so this division is safe
            eps = (sample - ab_t.sqrt() * x0) / (1 - ab_t).sqrt()
        else:
            raise ValueError(f"unknown prediction type {prediction!r}")
        if prev_t < 0:
            return x0
        ab_p = self._ab(torch.tensor([prev_t]), sample)
        return ab_p.sqrt() * x0 + (1 - ab_p).sqrt() * eps
