"""Stability cases outside the rasterizer: training NaN guard, scene scale, camera layouts."""

import math

import numpy as np
import pytest
import torch

from wgs.config import TrainConfig
from wgs.errors import WgsError
from wgs.gaussians.splats import create_splats
from wgs.gaussians.trainer import train_gaussians
from wgs.scene.convention import normalisation_from_cameras
from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at


def ring_w2c(n=4, radius=1.0, height=0.3, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n + jitter * rng.normal()
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height * radius])
        out.append(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])))
    return out


def test_nan_in_training_stops_with_iteration_and_group():
    f = Frame("a.png", torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]),
              torch.tensor(ring_w2c()[0], dtype=torch.float32), 16, 16, torch.full((16, 16, 3), float("nan")))
    sp = create_splats(torch.randn(50, 3) * 0.1, torch.rand(50, 3), torch.full((50,), 0.05), 0)
    cfg = TrainConfig(iterations=5, refine_start=100, floater_every=0, log_every=1)
    with pytest.raises(WgsError, match="non-finite at iteration 1"):
        train_gaussians(sp, [f], cfg, torch.device("cpu"), extent=1.0, has_masks=False)


@pytest.mark.parametrize("unit", [1e-3, 1.0, 1e4])
def test_normalisation_is_scale_invariant(unit):
    """Scenes in millimetres or kilometres normalise to the same cameras (up to float rounding)."""
    base = ring_w2c(jitter=0.2)
    scaled = []
    for m in base:
        s = m.copy()
        s[:3, 3] *= unit
        scaled.append(s)
    a, b = normalisation_from_cameras(base), normalisation_from_cameras(scaled)
    assert b.scale == pytest.approx(a.scale * unit, rel=1e-9)
    for m, s in zip(base, scaled, strict=True):
        np.testing.assert_allclose(b.w2c_to_normalised(s), a.w2c_to_normalised(m), atol=1e-9)


def test_nearly_collinear_cameras_give_a_finite_centre():
    """All cameras on one line, looking the same way: the axes barely intersect; the centre stays finite."""
    ws = []
    for i in range(4):
        eye = np.array([i * 1e-3, 0.0, -2.0])
        ws.append(look_at(eye, eye + np.array([1e-6 * i, 0, 1.0]), np.array([0.0, -1.0, 0.0])))
    n = normalisation_from_cameras(ws)
    assert np.isfinite(n.center).all() and np.isfinite(n.scale) and n.scale > 0
