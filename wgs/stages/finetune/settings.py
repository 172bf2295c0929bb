"""The finetune stage's settings, its facts for the registry and its cost model."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...cost import D_STEP_BATCH, D_STEP_CHANNELS, D_STEP_CROP, Calibration, SceneFacts, StageCost
from ...fields import option
from ..stage import Stage, StageEnv

FACTOR = 1.75  # time / modelled D steps on whole runs (lego at 200 px, ethiopianHead at 307 px; docs/speed.md)
# the HF U-Net U's step in D steps; U is modelled at the fewest steps its early stop allows
# (`u_patience` checks that do not beat no repair): 250 of 1500 on 8 of 11 runs of 10 kinds of
# capture, all 1500 on ethiopianHead, a vase in a room and a table close-up (docs/speed.md)
U_STEP_SHARE = 0.3
HELD_OUT_PAIRS = 44  # D's held-out check runs on about this many of G_d's pairs times `holdout`


@dataclass
class FinetuneConfig:
    """The LL-domain repair diffusion model D and the HF U-Net U."""

    domain: str = option(
        "wavelet",
        "wavelet: D repairs the LL subband and U the HF ones; rgb: D on RGB, no U.",
        choices=("wavelet", "rgb"),
    )
    levels: int = option(1, "Haar levels J (D at 1/2^J resolution).")
    diffusion: str = option(
        "embedded",
        "embedded: our CPU-sized denoiser; controlnet: SD 1.5 + ControlNet-tile + LoRA.",
        choices=("embedded", "controlnet"),
    )
    sd_model: str | None = option(None, "Local Stable Diffusion 1.5 folder.", metavar="DIR")
    controlnet: str | None = option(None, "Local ControlNet-tile folder.", metavar="DIR")
    lora_rank: int = 64
    lora_lr: float = 1e-3
    lora_steps: int = 500
    lora_crop: int = 64
    use_u: bool = option(True, "Train and use the HF U-Net U.", flags=("--u/--no-u",))
    prior: str = option(
        "builtin",
        "Start D and U from the pretrained repair prior (builtin), train them from scratch (none), or from a prior "
        "folder with D/ and U/.",
        metavar="builtin|none|DIR",
    )
    prior_steps: int = option(
        150, "Fine-tune steps of the prior's D on this object's pairs (0: the prior as shipped).", bounds=(0, None)
    )
    prior_lr: float = 5e-5
    prior_eval_every: int = 25
    prior_patience: int = 4  # held-out checks that do not beat the best before D stops
    # a check beats the best only by lowering its held-out MSE by more than this share of it
    prior_min_gain: float = option(0.0, bounds=(0.0, 1.0))
    train_timesteps: int = 1000
    d_channels: int = 32  # base width; the U-Net uses (c, 2c, 2c)
    d_steps: int = option(1500, "Training steps of D.")
    d_batch: int = 16
    d_crop: int = 32
    d_lr: float = 2e-4
    ema_decay: float = 0.995
    u_channels: int = 16
    u_max_steps: int = option(1500, "Step limit of U (early stopping ends it sooner).")
    u_batch: int = 16
    u_crop: int = 32
    u_lr: float = 1e-3
    u_eval_every: int = 50
    u_patience: int = 5
    # a held-out check beats U's best only by lowering its L1 by more than this share of it, so that
    # U stops where it gains less per `u_patience` checks (0: every gain counts; 0.02 saves 26-45 s
    # where U trains all its steps, at a cost in G_f on one of two captures: docs/what-we-tried.md)
    u_min_gain: float = 0.0
    holdout: float = 0.15  # fraction of pairs kept out of training to measure D
    eval_strength: float = 0.5  # SDEdit strength of the held-out check
    eval_steps: int = 10


def run(ws: Any, cfg: FinetuneConfig, env: StageEnv, force: bool) -> bool:
    from .run import run_finetune  # on first use: the stage loads the library

    return run_finetune(ws, cfg, env, force)


def d_pixels(cfg: FinetuneConfig, facts: SceneFacts) -> float:
    """The pixels of D's input for a render: the LL subband's in the wavelet domain, else the render's."""
    return facts.pixels / 4**cfg.levels if cfg.domain == "wavelet" else facts.pixels


def cost(cal: Calibration, cfgs: Mapping[str, Any], facts: SceneFacts, before: Mapping[str, float]) -> StageCost:
    """D's steps (the prior's few, or a from-scratch D's), U's, and D's held-out checks."""
    ft: FinetuneConfig = cfgs["finetune"]
    d_steps = ft.prior_steps if ft.prior != "none" else ft.d_steps
    width = (ft.d_channels / D_STEP_CHANNELS) ** 2 * (ft.d_batch * ft.d_crop**2) / (D_STEP_BATCH * D_STEP_CROP**2)
    u_steps = min(ft.u_max_steps, ft.u_patience * ft.u_eval_every) if ft.use_u and ft.domain == "wavelet" else 0
    # D's held-out check: SDEdit on the held-out pairs every prior_eval_every steps
    checks = (
        (d_steps // max(ft.prior_eval_every, 1) + 1)
        * math.ceil(HELD_OUT_PAIRS * ft.holdout)
        * math.ceil(ft.eval_steps * ft.eval_strength)
    )
    steps_s = cal.d_step_s * (FACTOR * d_steps * width + u_steps * U_STEP_SHARE)
    return StageCost(fixed_steps=20, other_s=steps_s + checks * d_pixels(ft, facts) * cal.d_forward_s_per_pixel)


STAGE = Stage(
    "finetune",
    "3_finetune",
    FinetuneConfig,
    ("coarse", "mask_data"),
    run,
    "Fine-tune the repair model D (from the pretrained prior) and the HF U-Net U on this object.",
    cost,
    outputs={"models": "."},  # D/ (or D_lora/) and U/
    presets={
        "fast": {
            "d_steps": 300,
            "u_max_steps": 100,
            "d_channels": 16,
            "u_eval_every": 25,
            "u_patience": 2,
            "prior_steps": 15,
        }
    },
    all_options=("domain", "use_u", "prior"),
)
