"""Where a training run stops gaining, from a held-out score measured during it.

A sparse-view model overfits its few photos: its novel views get better for a few hundred
iterations and then worse (the report's test probe peaks at iteration 250 of 1500 on an
all-around capture). A real capture has no test views, so the evidence comes from the photos:
pilots that each hold one training photo out and score the model there while it trains. Their
mean curve says where the scene stopped gaining; the full run stops there.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

from ..fields import option

Curve = list[tuple[int, float]]  # (iteration, held-out score in dB), iterations increasing
STOP_RULES = ("held-out", "iterations")  # the training stages' `stop` choices


@dataclass
class StopRule:
    """Whether a training stage stops where the held-out rule says: the one place its default
    lives (the coarse stage runs the pilots, the fine stage follows them)."""

    stop: str = option(
        "held-out",
        "held-out: pilots that each hold one photo out (half size, in the coarse stage) choose where the models "
        "stop gaining; iterations: train all the iterations.",
        choices=STOP_RULES,
    )


@dataclass
class StopParams(StopRule):
    """The held-out stopping rule's settings: the one place their defaults live (the training
    stages' configs inherit these fields)."""

    stop_every: int = 25  # a pilot scores its held-out photo every so many iterations
    stop_tolerance_db: float = 0.1  # a score within this of the best counts as the best
    stop_patience: int = 250  # a pilot ends after this many iterations without a better score (or at `pilot_cap`)
    stop_min_iterations: int = 100  # the full run trains at least this many iterations
    stop_pilots: int = 4  # at most this many pilots, their held-out photos spread over the photos' order
    # the full run trains this many times the pilots' plateau: a photo held out 90 degrees from the
    # others stops gaining before the views between the photos do (lego, 4 photos: the pilots'
    # plateau at 400, the test views' gain ends near 1000; README, "Where training stops")
    stop_margin: float = 3.0


def pilot_cap(iterations: int, margin: float, patience: int) -> int:
    """The most iterations a pilot needs: a plateau past `iterations / margin` leaves the full run
    at all its `iterations`, and seeing a plateau there takes `patience` more iterations. Past
    this point a pilot's curve cannot shorten the run."""
    return min(iterations, math.ceil(iterations / margin) + patience)


def stop_iteration(plateau: int, margin: float, min_iterations: int, iterations: int) -> int:
    """Where a run of `iterations` stops under the held-out rule: `margin` times the pilots'
    `plateau`, at least `min_iterations`."""
    return min(max(round(margin * plateau), min_iterations), iterations)


def plateau_iteration(curve: Curve, tolerance_db: float) -> int:
    """The first iteration whose score is within `tolerance_db` of the curve's best: where the
    gain ends (later iterations add less than the tolerance, or lose)."""
    best = max(s for _, s in curve)
    return next(it for it, s in curve if s >= best - tolerance_db)


def smoothed(curve: Curve, window: int) -> Curve:
    """Each score replaced by the mean of those in the `window` iterations up to it (densification
    every `refine_every` iterations dips the score for a few probes)."""
    return [(it, statistics.fmean(s for i, s in curve if it - window < i <= it)) for it, _ in curve]


def still_gaining(curve: Curve, tolerance_db: float, patience: int) -> bool:
    """Whether the curve beat its best by more than `tolerance_db` within its last `patience`
    iterations (always True before it is `patience` long)."""
    last = curve[-1][0]
    if last < patience:
        return True
    best_before = max((s for it, s in curve if it <= last - patience), default=float("-inf"))
    return any(s > best_before + tolerance_db for it, s in curve if it > last - patience)


def plateau_past(curve: Curve, point: float, tolerance_db: float) -> bool:
    """Whether the curve already shows that its plateau lies past iteration `point`: a later score
    beats every score up to `point` by more than `tolerance_db`. A pilot that shows it for the
    point past which every plateau leaves the run all its iterations (`iterations / margin`) has
    nothing more to say. When every pilot ends so, their mean curve's last score also beats its
    scores up to `point` by more than the tolerance."""
    before = max((s for it, s in curve if it <= point), default=math.inf)
    return any(s > before + tolerance_db for it, s in curve if it > point)


def mean_curve(curves: list[Curve]) -> Curve:
    """The pilots' mean curve at their common probe iterations; a pilot that ended earlier (it had
    stopped gaining) counts with its last score after its end."""
    its = sorted({it for c in curves for it, _ in c})

    def at(c: Curve, it: int) -> float:
        return next((s for i, s in reversed(c) if i <= it), c[0][1])

    return [(it, statistics.fmean(at(c, it) for c in curves)) for it in its]


__all__ = [
    "STOP_RULES",
    "Curve",
    "StopParams",
    "StopRule",
    "mean_curve",
    "pilot_cap",
    "plateau_iteration",
    "plateau_past",
    "smoothed",
    "still_gaining",
    "stop_iteration",
]
