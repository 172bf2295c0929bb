"""Quality against training time: the probe inside the training loop and the files it leaves."""

from __future__ import annotations

import time

import torch
from conftest import ring_w2c

from wgs.curves import probe_views
from wgs.gaussians.callbacks import Probe
from wgs.gaussians.splats import create_splats
from wgs.gaussians.trainer import TrainConfig, train_gaussians
from wgs.scene.dataset import Frame


def tiny_training(probe, iterations=5):
    f = Frame(
        torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]),
        torch.tensor(ring_w2c()[0], dtype=torch.float32),
        16,
        16,
        name="a.png",
        image=torch.rand(16, 16, 3),
    )
    sp = create_splats(torch.randn(40, 3) * 0.1, torch.rand(40, 3), torch.full((40,), 0.05), 0)
    cfg = TrainConfig(iterations=iterations, refine_start=100, floater_every=0, log_every=1)
    return train_gaussians(sp, [f], cfg, torch.device("cpu"), extent=1.0, has_masks=False, probe=probe)


def test_probe_points_at_start_every_interval_and_end_and_its_time_is_not_training_time():
    calls = []

    def fn(splats):
        calls.append(splats["means"].shape[0])
        time.sleep(0.1)
        return {"psnr": float(len(calls))}

    t0 = time.perf_counter()
    res = tiny_training(Probe(fn, every_s=0.0, max_share=float("inf")))  # every iteration
    wall = time.perf_counter() - t0
    assert [p["iteration"] for p in res.curve] == [0, 1, 2, 3, 4, 5]
    assert [p["psnr"] for p in res.curve] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    secs = [p["seconds"] for p in res.curve]
    assert secs == sorted(secs) and secs[-1] <= res.seconds
    assert res.probe_seconds >= 0.6 and res.seconds < wall - 0.5  # the sleeps are not training time


def test_a_slow_probe_stays_a_small_share_of_the_training_time():
    """A probe that costs much against its interval is spaced out to `max_share` of the training
    time, start and end kept; the model trains the same as with a probe every iteration."""

    def slow(splats):
        time.sleep(0.01)
        return {"psnr": 1.0}

    torch.manual_seed(0)
    capped = tiny_training(Probe(slow, every_s=0.0, max_share=0.1), iterations=150)
    torch.manual_seed(0)
    every = tiny_training(Probe(slow, every_s=0.0, max_share=float("inf")), iterations=150)
    assert len(every.curve) == 151 and capped.curve[0]["iteration"] == 0 and capped.curve[-1]["iteration"] == 150
    assert len(capped.curve) < 151
    # after a probe of p seconds the next waits p / 0.1 training seconds: the probes at the start and
    # the end, and at most a tenth of the training time between
    assert capped.probe_seconds <= 0.1 * capped.seconds + 2 * 0.02
    assert all(torch.equal(capped.splats[k], every.splats[k]) for k in every.splats)


def test_sparse_probe_keeps_start_and_end():
    res = tiny_training(Probe(lambda s: {"psnr": 1.0}, every_s=1e9), iterations=4)
    assert [p["iteration"] for p in res.curve] == [0, 4]


def test_probe_every_so_many_iterations_on_a_fast_run():
    """A run faster than the probe interval still gets a curve: a point every `every_iterations`."""
    res = tiny_training(Probe(lambda s: {"psnr": 1.0}, every_s=1e9, every_iterations=3), iterations=10)
    assert [p["iteration"] for p in res.curve] == [0, 3, 6, 9, 10]


def test_no_probe_no_curve():
    res = tiny_training(None)
    assert res.curve == [] and res.probe_seconds == 0.0


def test_probe_views_spread_over_the_test_set():
    names = [f"v{i}" for i in range(10)]
    assert probe_views(names, 4) == [0, 3, 6, 9]
    assert probe_views(names[:2], 4) == [0, 1]
    assert probe_views(names, 0) == [] and probe_views([], 4) == []
    assert probe_views(names, 1) == [0]
