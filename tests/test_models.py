"""Repair models: scheduler closed forms, DDIM stability, tiny-model training, storage, early stopping."""

import math

import pytest
import torch

from wgs.errors import InputError
from wgs.models.hf_unet import HFUNet, HFUNetConfig
from wgs.models.ll_denoiser import LLDenoiser, LLDenoiserConfig
from wgs.models.sampling import sdedit_repair
from wgs.models.scheduler import DDIMScheduler
from wgs.models.storage import load_model, save_model
from wgs.stages.finetune.settings import FinetuneConfig
from wgs.training.loop import FitPlan
from wgs.training.per_object import train_hf_unet, train_scratch_d
from wgs.wavelet.haar import dwt2, idwt2


def test_add_noise_and_velocity_closed_form():
    s = DDIMScheduler(10, beta_start=0.01, beta_end=0.04)
    t = torch.tensor([3])
    ab = float(s.alphas_cumprod[3])
    x0, n = torch.tensor([[0.5]]), torch.tensor([[-2.0]])
    torch.testing.assert_close(s.add_noise(x0, n, t), torch.tensor([[math.sqrt(ab) * 0.5 - math.sqrt(1 - ab) * 2.0]]))
    torch.testing.assert_close(
        s.get_velocity(x0, n, t), torch.tensor([[math.sqrt(ab) * -2.0 - math.sqrt(1 - ab) * 0.5]])
    )


def test_untrained_denoiser_is_the_identity_repair():
    model = LLDenoiser(LLDenoiserConfig(3, 8, 16))
    cond = torch.rand(1, 3, 9, 9)
    out = sdedit_repair(model, DDIMScheduler(100), cond, 0.5, 4, torch.Generator().manual_seed(0))
    torch.testing.assert_close(out, cond)


def test_denoiser_training_lowers_the_loss():
    g = torch.Generator().manual_seed(0)
    clean = torch.rand(4, 3, 16, 16, generator=g) * 2 - 1
    bad = clean + 0.3 * torch.randn(4, 3, 16, 16, generator=g)
    cfg = FinetuneConfig(d_channels=8, d_steps=120, d_batch=4, d_crop=16, d_lr=2e-3, ema_decay=0.9)
    _, curve, meta = train_scratch_d(cfg, clean, bad, torch.device("cpu"), g)
    assert meta.start == "clean" and meta.train_timesteps == cfg.train_timesteps
    assert curve["loss"][-1] < 0.7 * curve["loss"][0]


def test_shapes_and_exceptions():
    m = LLDenoiser(LLDenoiserConfig(3, 8, 16))
    assert m(torch.zeros(1, 3, 7, 9), torch.zeros(1), torch.zeros(1, 3, 7, 9)).shape == (1, 3, 7, 9)
    with pytest.raises(ValueError, match="must match"):
        m(torch.zeros(1, 3, 8, 8), torch.zeros(1), torch.zeros(1, 3, 4, 4))
    u = HFUNet(HFUNetConfig(channels=8))
    assert u(torch.zeros(2, 9, 5, 6), torch.zeros(2, 3, 5, 6)).shape == (2, 9, 5, 6)
    with pytest.raises(ValueError):
        DDIMScheduler(10).set_timesteps(0)


def test_save_and_reload_reproduce_the_output(tmp_path):
    m = LLDenoiser(LLDenoiserConfig(3, 8, 16))
    with torch.no_grad():
        for p in m.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    save_model(tmp_path / "D", m)
    m2, cfg = load_model(tmp_path / "D")
    x, c, t = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8), torch.tensor([10])
    torch.testing.assert_close(m2(x, t, c), m.eval()(x, t, c))
    assert cfg["class"] == "LLDenoiser"
    (tmp_path / "D" / "model.safetensors").write_bytes(b"junk")
    with pytest.raises(InputError, match="model.safetensors"):
        load_model(tmp_path / "D")


def test_u_early_stopping_stops_when_validation_rises():
    # HF repair that cannot generalise: train and held-out views have opposite corrections
    g = torch.Generator().manual_seed(0)
    refs = torch.rand(3, 3, 32, 32, generator=g)
    renders = refs.clone()
    renders[:2] += 0.2 * torch.randn(2, 3, 32, 32, generator=g)
    cfg = FinetuneConfig(u_channels=8, u_max_steps=2000, u_batch=4, u_crop=8, u_lr=5e-3, u_eval_every=10, u_patience=3)
    _, curve = train_hf_unet(cfg, renders, refs, torch.device("cpu"), g)
    assert curve["stopped_at"] < 2000
    vals = [curve["bar"], *curve["val"]]  # the better of no repair and the untrained U is the first candidate
    i_best = vals.index(min(vals))
    assert len(vals) - 1 - i_best == 3  # stopped after `patience` evaluations without improvement
    assert curve["best"] == min(vals) <= curve["identity"]
    assert not curve["beats_identity"]  # the held-out view needs no HF repair: U is left out


def test_u_stops_where_its_held_out_gain_falls_below_u_min_gain():
    """A correction U keeps learning: with every gain counted it trains all its steps; with
    `u_min_gain` 0.3 a check beats the best only by lowering it 30 %, so U stops sooner, after
    `u_patience` checks that did not, and keeps the last state that did."""
    g = torch.Generator().manual_seed(0)
    renders = torch.rand(4, 3, 32, 32, generator=g) * 2 - 1
    ll, [h] = dwt2(renders, 1)
    refs = idwt2(ll, [tuple(0.5 * b for b in h)])

    def fit(min_gain: float) -> dict:
        cfg = FinetuneConfig(
            u_channels=8, u_max_steps=200, u_batch=4, u_crop=8, u_lr=5e-3, u_eval_every=20, u_patience=2,
            u_min_gain=min_gain,
        )  # fmt: skip
        return train_hf_unet(cfg, renders, refs, torch.device("cpu"), torch.Generator().manual_seed(0))[1]

    every, coarse = fit(0.0), fit(0.3)
    assert every["stopped_at"] == 200 and coarse["stopped_at"] < 200
    assert all(v >= 0.7 * coarse["best"] for v in coarse["val"][-2:])  # the last 2 checks did not count
    assert coarse["best"] >= min(coarse["val"])  # a smaller score that did not count is not kept
    assert FitPlan(10, 1e-3, 5, min_delta=1e-7, min_gain=0.02).margin(0.01) == pytest.approx(1e-7 + 2e-4)
    assert FitPlan(10, 1e-3, 5, min_gain=0.02).margin(math.inf) == FitPlan(10, 1e-3, 5).min_delta  # no bar yet


def test_u_that_learns_a_consistent_correction_beats_identity():
    # every view's reference has its HF halved: a correction that generalises to the held-out view
    g = torch.Generator().manual_seed(0)
    renders = torch.rand(4, 3, 32, 32, generator=g) * 2 - 1
    ll, [h] = dwt2(renders, 1)
    refs = idwt2(ll, [tuple(0.5 * b for b in h)])
    cfg = FinetuneConfig(u_channels=8, u_max_steps=300, u_batch=4, u_crop=8, u_lr=5e-3, u_eval_every=20, u_patience=3)
    _, curve = train_hf_unet(cfg, renders, refs, torch.device("cpu"), g)
    assert curve["beats_identity"] and curve["best"] < 0.8 * curve["identity"]
