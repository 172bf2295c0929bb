"""What the 3DGS training loop (`trainer.train_gaussians`) does besides a training step, one small
piece each, as nerfstudio's training callbacks: the clock that leaves the probes' time out, the
time box, the probe points, and the state a snapshot saves and a resume restores. The pseudo
views' loss term is `trainer.PseudoViews`'s."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..resume import rng_state, set_rng_state
from .pose_refine import CameraCorrections
from .splats import Splats


class TrainingClock:
    """Training seconds: the wall time since the loop started (the time before a resume counted),
    less what was left out of it (the probes' own time)."""

    def __init__(self, elapsed: float = 0.0):
        self.t0 = time.perf_counter() - elapsed

    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def leave_out(self, seconds: float) -> None:
        self.t0 += seconds


@dataclass(frozen=True)
class TimeBox:
    """A loop that ends after `max_seconds` of training (None: no time box): its schedules
    (learning rate, densification, half size, SH degree) follow the elapsed share of the time
    instead of the iteration count, over `iterations`."""

    iterations: int
    max_seconds: float | None

    def schedule(self, it: int, clock: TrainingClock) -> int:
        """The schedule's position at iteration `it`: `it`, or further along as the time goes."""
        if not self.max_seconds:
            return it
        return max(it, int(self.iterations * clock.seconds() / self.max_seconds))

    def over(self, clock: TrainingClock) -> bool:
        return bool(self.max_seconds and clock.seconds() > self.max_seconds)


@dataclass
class Probe:
    """Quality during training: fn(splats) -> metrics (e.g. test PSNR), run every `every_s` seconds
    of training time (and every `every_iterations` iterations when > 0), at the start and at the
    end; its own time is left out of the training clock. A probe that took p seconds is followed by
    the next one no sooner than p / `max_share` training seconds later, so that on large views
    (ethiopianHead at 666 px: 4.8 s a probe) probing stays a small share of the wall time."""

    fn: Callable[[Splats], dict[str, float]]
    every_s: float
    every_iterations: int = 0
    max_share: float = 0.1
    stop: Callable[[list[dict[str, float]]], bool] | None = None  # after a probe: True ends the loop


class ProbePoints:
    """A `Probe`'s points along one loop (seconds, iteration and metrics each; `curve`), and the
    seconds they took (`seconds`), left out of `clock`."""

    def __init__(
        self, probe: Probe | None, clock: TrainingClock, curve: list[dict[str, float]] | None = None, seconds=0.0
    ):
        self.probe, self.clock = probe, clock
        self.curve: list[dict[str, float]] = list(curve or [])
        self.seconds = seconds
        self.every_s = probe.every_s if probe is not None else 0.0

    def measure(self, params: Splats, it: int) -> None:
        """One point; the clock is moved on by the probe's own time."""
        assert self.probe is not None
        start = time.perf_counter()
        with torch.no_grad():
            metrics = self.probe.fn({k: v.detach() for k, v in params.items()})
        self.curve.append({"seconds": start - self.clock.t0, "iteration": it, **metrics})
        took = time.perf_counter() - start
        self.clock.leave_out(took)
        self.seconds += took
        self.every_s = max(self.probe.every_s, took / self.probe.max_share)

    def at_start(self, params: Splats, it: int) -> None:
        """The first point, unless a resumed loop has it."""
        if self.probe is not None and not self.curve:
            self.measure(params, it)

    def after_step(self, params: Splats, it: int, finished: bool) -> bool:
        """A point when one is due (and at the end); returns whether the loop ends: `finished`, or the
        probe's stop rule said so after this point."""
        probe = self.probe
        if probe is None:
            return finished
        last = self.curve[-1]
        if (
            finished
            or self.clock.seconds() - last["seconds"] >= self.every_s
            or 0 < probe.every_iterations <= it - last["iteration"]
        ):
            self.measure(params, it)
            return finished or bool(probe.stop and probe.stop(self.curve))
        return finished


@dataclass
class LoopState:
    """What the loop carries from one iteration to the next, saved whole by `snapshot` and put back
    by `restore` (a resumed loop then continues bit-identically): the parameters and their Adam
    moments, the densification state, the random generators, the views' order, the losses, the
    iteration and schedule position, the clock and the probe points, the cameras' corrections."""

    params: Splats
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: dict[str, Any]
    generator: torch.Generator
    clock: TrainingClock
    probes: ProbePoints
    cameras: CameraCorrections | None = None
    losses: list[float] = field(default_factory=list)
    order: list[int] = field(default_factory=list)
    it: int = 0
    sched: int = 0
    finished: bool = False

    def snapshot(self, moments: bool = False) -> dict[str, Any]:
        """The state on the CPU; a finished loop's without the moments (the size of the model)
        unless `moments`."""
        out = {
            "params": {k: v.detach().cpu() for k, v in self.params.items()},
            "generator": self.generator.get_state(),
            "rng": rng_state(),
            "losses": self.losses,
            "order": self.order,
            "it": self.it,
            "sched": self.sched,
            "elapsed": self.clock.seconds(),
            "finished": self.finished,
            "curve": self.probes.curve,
            "probe_s": self.probes.seconds,
        }
        if self.cameras is not None:
            out["cameras"] = self.cameras.state_dict()
        if moments or not self.finished:
            out["optimizers"] = {k: o.state_dict() for k, o in self.optimizers.items()}
            out["strategy"] = {k: (None if v is None else v.cpu()) for k, v in self.strategy.items()}
        return out

    def restore(
        self,
        saved: dict[str, Any],
        device: torch.device,
        make_optimizers: Callable[[Splats], dict[str, torch.optim.Optimizer]],
    ) -> None:
        """Put a snapshot back: new optimizers for the saved parameters (`make_optimizers`), with
        their moments unless the loop had finished."""
        self.params = {k: v.to(device).requires_grad_(True) for k, v in saved["params"].items()}
        self.optimizers = make_optimizers(self.params)
        if not saved["finished"]:
            for k, opt in self.optimizers.items():
                opt.load_state_dict(saved["optimizers"][k])
            self.strategy = {k: (None if v is None else v.to(device)) for k, v in saved["strategy"].items()}
        self.generator.set_state(saved["generator"])
        set_rng_state(saved["rng"])
        self.losses, self.order = list(saved["losses"]), list(saved["order"])
        self.it, self.sched, self.finished = saved["it"], saved["sched"], saved["finished"]
        self.clock.leave_out(-saved["elapsed"])
        self.probes.curve, self.probes.seconds = list(saved.get("curve", [])), saved.get("probe_s", 0.0)
        if self.cameras is not None:
            self.cameras.load_state_dict(saved["cameras"])
