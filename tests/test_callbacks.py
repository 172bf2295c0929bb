"""The training loop's callbacks, each on its own (`wgs.gaussians.callbacks`): the clock, the time
box, the probe points, the state a snapshot saves and a resume restores; and the pseudo views'
cadence (`trainer.PseudoViews.due`). tests/test_resume.py checks that a loop resumed from a snapshot
ends bit-identically."""

import time

import pytest
import torch

from wgs.gaussians.callbacks import LoopState, Probe, ProbePoints, TimeBox, TrainingClock
from wgs.gaussians.trainer import PseudoViews, TrainConfig, make_optimizers


def clock_at(seconds: float) -> TrainingClock:
    return TrainingClock(elapsed=seconds)


def test_the_clock_counts_from_its_start_and_leaves_out_what_it_is_told():
    clock = clock_at(10.0)
    assert 10.0 <= clock.seconds() < 10.5
    clock.leave_out(4.0)
    assert 6.0 <= clock.seconds() < 6.5


def test_a_time_box_moves_the_schedule_with_the_time_and_ends_the_loop():
    none = TimeBox(1000, None)
    assert none.schedule(7, clock_at(1e6)) == 7 and not none.over(clock_at(1e6))
    box = TimeBox(1000, 100.0)
    assert box.schedule(7, clock_at(50.0)) == 500  # half the time: half the schedule
    assert box.schedule(700, clock_at(50.0)) == 700  # never behind the iteration count
    assert not box.over(clock_at(50.0)) and box.over(clock_at(101.0))


def slow_probe(took: float, **kw) -> Probe:
    def fn(params):
        time.sleep(took)
        return {"psnr": float(params["x"].sum())}

    return Probe(fn, **kw)


def test_a_probe_point_is_left_out_of_the_clock_and_spaces_the_next():
    clock = TrainingClock()
    points = ProbePoints(slow_probe(0.05, every_s=0.01, max_share=0.1), clock)
    params = {"x": torch.ones(3)}
    points.at_start(params, 0)
    assert points.curve == [{"seconds": pytest.approx(0.0, abs=0.02), "iteration": 0, "psnr": 3.0}]
    assert clock.seconds() < 0.03 and points.seconds >= 0.05  # the probe's time is not training time
    assert points.every_s >= 0.5  # 0.05 s a probe at most a tenth of the time
    assert not points.after_step(params, 1, False) and len(points.curve) == 1  # not due yet
    assert points.after_step(params, 2, True) and len(points.curve) == 2  # the end always probes


def test_a_probe_is_due_every_so_many_iterations_and_its_stop_rule_ends_the_loop():
    clock = TrainingClock()
    stops = ProbePoints(slow_probe(0.0, every_s=1e6, every_iterations=5, stop=lambda c: len(c) >= 3), clock)
    params = {"x": torch.zeros(2)}
    stops.at_start(params, 0)
    ended = next(it for it in range(1, 20) if stops.after_step(params, it, False))
    assert [p["iteration"] for p in stops.curve] == [0, 5, 10] and ended == 10
    resumed = ProbePoints(slow_probe(0.0, every_s=1.0), TrainingClock(), curve=stops.curve)
    resumed.at_start(params, 10)
    assert len(resumed.curve) == 3  # a resumed loop keeps its points and does not probe again at once
    assert ProbePoints(None, clock).after_step(params, 3, False) is False


def loop_state(seed: int = 0) -> LoopState:
    gen = torch.Generator().manual_seed(seed)
    params = {
        k: torch.randn(5, *shape, generator=gen).requires_grad_(True)
        for k, shape in {
            "means": (3,),
            "quats": (4,),
            "scales": (3,),
            "opacities": (),
            "sh0": (1, 3),
            "shN": (3, 3),
        }.items()
    }
    clock = TrainingClock()
    return LoopState(
        params,
        make_optimizers(params, TrainConfig(), 1.0),
        {"grad2d": torch.rand(5, generator=gen), "count": None},
        gen,
        clock,
        ProbePoints(None, clock),
    )


def test_a_snapshot_restores_the_loop_exactly():
    a = loop_state()
    sum(p.square().sum() for p in a.params.values()).backward()
    for opt in a.optimizers.values():
        opt.step()
    a.losses[:] = [0.5, 0.25]
    a.order[:] = [3, 1]
    a.it, a.sched = 2, 4
    a.probes.curve.append({"seconds": 1.0, "iteration": 2, "psnr": 9.0})
    saved = a.snapshot()
    b = loop_state(seed=1)
    b.restore(saved, torch.device("cpu"), lambda p: make_optimizers(p, TrainConfig(), 1.0))
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    for k in a.optimizers:
        sa, sb = a.optimizers[k].state_dict()["state"][0], b.optimizers[k].state_dict()["state"][0]
        assert all(torch.equal(sa[m], sb[m]) for m in ("exp_avg", "exp_avg_sq", "step")), k
    assert torch.equal(b.strategy["grad2d"], a.strategy["grad2d"]) and b.strategy["count"] is None
    assert torch.equal(b.generator.get_state(), a.generator.get_state())
    assert (b.losses, b.order, b.it, b.sched, b.probes.curve) == ([0.5, 0.25], [3, 1], 2, 4, a.probes.curve)
    assert b.clock.seconds() >= saved["elapsed"]
    a.finished = True
    assert "optimizers" not in a.snapshot() and "strategy" not in a.snapshot()  # a finished loop: the model alone


def test_pseudo_views_are_due_on_their_cadence_while_their_schedule_weighs_them():
    pseudo = PseudoViews([], [], lambda sched: 1.0 if sched < 10 else 0.0, torch.ones(3), every=2)
    assert [it for it in range(1, 14) if pseudo.due(it, it)] == [2, 4, 6, 8]
