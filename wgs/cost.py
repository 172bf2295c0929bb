"""The pieces of the run-time model that each stage's cost model is made of (`Stage.cost`, in the
stage's own settings module); `wgs.estimate` calibrates them on this machine and adds them up.

A stage's time is its work in calibrated units (a training view's render and loss, forward and
backward; a training step of the repair network D and its forward pass) times a factor measured on
whole runs (docs/speed.md "Working size, estimate and budget"), plus a fixed part in D-step units.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from .gaussians.stopping import StopParams, stop_iteration
from .gaussians.trainer import TrainConfig

# the working size chosen for the machine where neither downscale nor max_size is set (wgs.estimate)
GPU_MAX_SIZE = 1600  # px, a GPU's long side at most (the 3DGS convention)
CPU_TARGET_S = 600.0  # a CPU's: the largest size at which `wgs all` is modelled to take about this long

# a training loop's time grows with the share of the frame the object covers (more Gaussians, more
# of them on each pixel), which the calibration's fixed synthetic cloud does not see: the training
# stages' factors are times 1 + MASK_SHARE_SLOPE x (mask share - FIT_MASK_SHARE), at least
# MIN_SHARE_FACTOR. FIT_MASK_SHARE: lego's 4 views, on which the stages' factors were fitted; the slope from one
# generated close-up (0.786 of its photos), checked on kinds of capture left out of that fit
# (docs/speed.md "The estimate on captures it was not fitted on")
FIT_MASK_SHARE = 0.245
MASK_SHARE_SLOPE = 1.4
MIN_SHARE_FACTOR = 0.5
# the training stages of a scene without masks: the background is reconstructed too, with about
# 4x the Gaussians (the fox at 213x379, 2026-11-27)
NO_MASKS_FACTOR = 1.9
# side-by-side coarse models (one thread each, `threads.side_by_side`) train this many
# times as fast, together, as one model on every thread (measured on 2 cores, wgs/threads.py)
SIDE_BY_SIDE_THROUGHPUT = 1.5
# Where the held-out stopping rule's pilots stop gaining, for the estimate made before they run,
# where the hull's leave-one-out IoU is not known (no masks; the working-size chooser, before
# prepare): the median over seven kinds of capture (125-700: lego 400, a generated object 45 degrees
# apart 425, close-ups 125 and 625, no masks 625, all around 700 and 700; docs/speed.md), so that
# such a capture trains all its iterations, as its stop at 3 x 625 says
EXPECTED_PLATEAU = 625
# Where it is known (prepare's mirror check: how well the hull of the other photos predicts each
# photo's mask), a hull that predicts the photos poorly leaves the models to overfit them sooner:
# the plateau on the line through these two (IoU, plateau) points, clamped between their plateaus;
# fitted on six kinds of capture (docs/speed.md, "The plateau expected from the hull")
HULL_PLATEAU_LINE = ((0.72, 125), (0.88, EXPECTED_PLATEAU))
D_STEP_BATCH, D_STEP_CROP, D_STEP_CHANNELS = 16, 32, 32  # the D training step timed


@dataclass(frozen=True)
class Calibration:
    """Timings on this machine: a training view's rasterizer and photometric loss, forward and
    backward, as `intercept + slope * pixels` seconds; D's training step (batch 16 of 32x32 crops, 32 channels) and D's
    forward pass per pixel of its input."""

    raster: tuple[float, float]
    d_step_s: float
    d_forward_s_per_pixel: float
    threads: int
    device: str
    seconds: float

    def view_s(self, pixels: float) -> float:
        intercept, slope = self.raster
        return intercept + slope * pixels


@dataclass(frozen=True)
class SceneFacts:
    """What a scene's cost depends on: its working size (px), its training and test views, its
    photos' size before downscaling (prepare reads them), and whether it has masks."""

    width: int
    height: int
    n_train: int
    n_test: int
    full_pixels: int = 0
    has_masks: bool = True
    posed_by_wgs: bool = False  # photos posed by prepare: eval localises the test cameras
    mask_share: float = FIT_MASK_SHARE  # the share of a training photo inside its mask (prepare's record)
    plateau: int | None = None  # the coarse pilots' plateau once they ran (before: `expected_plateau`)
    expected_plateau: int = EXPECTED_PLATEAU  # where they are expected to find it (`plateau_from_hull`)
    pilot_ends: tuple[int, ...] = ()  # where each of those pilots ended, in their order (once they ran)

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def plateau_or_expected(self) -> int:
        """The pilots' plateau once they ran, else where they are expected to find it."""
        return self.expected_plateau if self.plateau is None else self.plateau


@dataclass(frozen=True)
class StageCost:
    """A stage's modelled seconds: `fixed_steps` (loading, renders, files) in D training steps, then
    for a training stage `loops` training loops run one after another, each `loop_s` seconds times
    `factor` (time / modelled work, measured on whole runs), and `other_s` for the rest of its work."""

    fixed_steps: float
    other_s: float = 0.0
    loops: int = 0
    loop_s: float = 0.0
    factor: float = 1.0

    def seconds(self, cal: Calibration, max_seconds: float | None = None) -> float:
        """The stage's seconds; `max_seconds`: a time-boxed loop's own limit."""
        loop, factor = self.loop_s, self.factor
        if max_seconds:
            loop, factor = min(loop * factor, max_seconds), 1.0
        return self.fixed_steps * cal.d_step_s + self.loops * loop * factor + self.other_s


def time_boxed(cfg: Any, seconds: float, planned_seconds: float, headroom: float) -> Any:
    """`cfg` (a TrainConfig) stopped after `seconds` of training: its iteration and densification
    caps scaled by the time over `planned_seconds` (what its own iterations take) times `headroom`,
    so that the time, not the caps, ends it; its schedules then follow the elapsed fraction."""
    scale = max(1.0, seconds / max(planned_seconds, 1e-6)) * headroom
    return dataclasses.replace(
        cfg, iterations=int(cfg.iterations * scale), refine_stop=int(cfg.refine_stop * scale), max_seconds=seconds
    )


def plateau_from_hull(loo_iou: float | None) -> int:
    """Where the held-out rule's pilots are expected to find the scene's plateau, before they run,
    from the training photos' leave-one-out silhouette IoU (`HULL_PLATEAU_LINE`); EXPECTED_PLATEAU
    without one."""
    if loo_iou is None:
        return EXPECTED_PLATEAU
    (x0, y0), (x1, y1) = HULL_PLATEAU_LINE
    return round(min(max(y0 + (y1 - y0) * (loo_iou - x0) / (x1 - x0), y0), y1))


def expected_iterations(cfg: TrainConfig, plateau: int = EXPECTED_PLATEAU) -> int:
    """The iterations a loop is expected to run: up to its `end_iteration` where that is set, all
    of them, or under the held-out stopping rule (`gaussians.stopping`) its margin times the
    expected `plateau`."""
    if cfg.end_iteration:
        return min(cfg.end_iteration, cfg.iterations)
    if not isinstance(cfg, StopParams) or cfg.stop != "held-out" or cfg.max_seconds:
        return cfg.iterations
    return stop_iteration(plateau, cfg.stop_margin, cfg.stop_min_iterations, cfg.iterations)


def expected_follow_end(cfg: TrainConfig, coarse: TrainConfig, plateau: int | None = None) -> int | None:
    """Where a stage that follows the coarse stage's stop (G_f: `StopRule` without pilots of its
    own) is expected to end: the coarse pilots' `plateau` (before they ran, the expected one) times
    their margin, of the stage's own iterations; None where it trains them all."""
    if getattr(cfg, "stop", None) != "held-out" or cfg.max_seconds or not isinstance(coarse, StopParams):
        return None
    if coarse.stop != "held-out" or coarse.max_seconds:
        return None
    found = EXPECTED_PLATEAU if plateau is None else plateau
    return stop_iteration(found, coarse.stop_margin, coarse.stop_min_iterations, cfg.iterations)


def cover_factor(facts: SceneFacts) -> float:
    """The training stages' factor for how much of the frame the object covers."""
    if not facts.has_masks:
        return NO_MASKS_FACTOR
    return max(MIN_SHARE_FACTOR, 1.0 + MASK_SHARE_SLOPE * (facts.mask_share - FIT_MASK_SHARE))


def loop_iterations(cfg: TrainConfig, start: int = 0, plateau: int = EXPECTED_PLATEAU) -> tuple[float, float]:
    """A training loop's expected iterations after `start` (where it carries on from another
    loop's state): (at half size, those in the first `half_size_until` of the schedule; at full
    size); `plateau`: where the held-out rule is expected to find the scene's."""
    ends = expected_iterations(cfg, plateau)
    start = min(start, ends)
    half_ends = min(ends, cfg.half_size_until * cfg.iterations)
    return max(half_ends - start, 0), ends - max(half_ends, start)


def loop_s(
    cal: Calibration,
    cfg: TrainConfig,
    pixels: float,
    renders: float = 1.0,
    start: int = 0,
    plateau: int = EXPECTED_PLATEAU,
) -> float:
    """One training loop's modelled seconds (`loop_iterations`)."""
    half, full = loop_iterations(cfg, start, plateau)
    return (half * cal.view_s(pixels / 4) + full * cal.view_s(pixels)) * renders


def side_by_side_share(workers: int) -> float:
    """A model's share of the time when `workers` models train side by side."""
    return workers / SIDE_BY_SIDE_THROUGHPUT if workers > 1 else 1.0
