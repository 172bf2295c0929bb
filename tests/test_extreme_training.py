"""Stability suite, training: Training that turns non-finite: stopped with the iteration and the parameter
group, nothing saved.

Every case and its pass criterion is listed in docs/stability.md."""

import pytest
import torch
from conftest import ring_w2c

from wgs.errors import WgsError
from wgs.gaussians.splats import create_splats
from wgs.gaussians.trainer import TrainConfig, train_gaussians
from wgs.resume import Checkpointer
from wgs.scene.dataset import Frame
from wgs.stages.finetune.settings import FinetuneConfig
from wgs.training.per_object import train_scratch_d


def test_nan_in_training_stops_with_iteration_and_group():
    f = Frame(
        torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]),
        torch.tensor(ring_w2c()[0], dtype=torch.float32),
        16,
        16,
        name="a.png",
        image=torch.full((16, 16, 3), float("nan")),
    )
    sp = create_splats(torch.randn(50, 3) * 0.1, torch.rand(50, 3), torch.full((50,), 0.05), 0)
    cfg = TrainConfig(iterations=5, refine_start=100, floater_every=0, log_every=1)
    with pytest.raises(WgsError, match="non-finite at iteration 1"):
        train_gaussians(sp, [f], cfg, torch.device("cpu"), extent=1.0, has_masks=False)


def test_parameter_overflow_names_the_group_and_saves_nothing(tmp_path):
    """A mean that overflowed to inf after iteration 1 (planted through the shared storage that
    on_step sees): iteration 2 stops, naming the group, and no state is saved."""
    f = Frame(
        torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]),
        torch.tensor(ring_w2c()[0], dtype=torch.float32),
        16,
        16,
        name="a.png",
        image=torch.rand(16, 16, 3),
    )
    sp = create_splats(torch.randn(50, 3) * 0.1, torch.rand(50, 3), torch.full((50,), 0.05), 0)
    cfg = TrainConfig(iterations=5, refine_start=100, floater_every=0, log_every=1)
    ck = Checkpointer(tmp_path / "state.pt", every_s=1e9, resume=False)

    def overflow(it, params):
        if it == 1:
            params["means"][0, 0] = float("inf")

    with pytest.raises(WgsError, match=r"parameter group\(s\) means\b.* became non-finite at iteration 2"):
        train_gaussians(sp, [f], cfg, torch.device("cpu"), extent=1.0, has_masks=False, checkpoint=ck, on_step=overflow)
    assert not ck.path.exists()


def test_denoiser_training_on_nan_pairs_stops_at_step_1():
    cfg = FinetuneConfig(d_steps=5, d_channels=8, d_batch=2, d_crop=8)
    clean = torch.full((3, 3, 16, 16), float("nan"))
    with pytest.raises(WgsError, match="non-finite at step 1"):
        train_scratch_d(cfg, clean, torch.zeros_like(clean), torch.device("cpu"), torch.Generator().manual_seed(0))
