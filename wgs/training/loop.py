"""The one training loop of the networks wgs trains (D, U, S and V), per object and for the prior.

A caller gives the loss of one batch (`batch_loss(step)`: it samples the batch from its own
generator), and optionally an evaluation on held-out data. The loop does the rest the same way for
every network: the learning-rate schedule, the step (gradient clip, non-finite check, EMA of the
weights), the curve, the best state and early stopping, and a state that can be saved and continued
bit for bit (parameters, EMA, optimiser moments, generators, counters).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol, TypeVar

import torch

from ..errors import WgsError
from ..models.optim import clipped_step


@dataclass
class FitPlan:
    """How long and how a network trains; every trainer builds one from its own config."""

    steps: int
    lr: float
    eval_every: int  # steps between curve records (and evaluations)
    warmup: int | None = None  # None: constant lr; else linear warm-up over this many steps, then cosine to 0
    ema_decay: float | None = None  # keep an EMA of the weights; it is what gets evaluated and returned
    max_norm: float | None = 1.0  # gradient-norm clip (None: no clip)
    patience: int | None = None  # stop after this many evaluations that do not beat the best
    keep_best: bool = False  # return the best evaluated state (else the last)
    min_delta: float = 1e-9  # an evaluation beats the best by more than this
    min_gain: float = 0.0  # and by more than this share of the best (a gain too small to pay for more steps)

    def margin(self, best: float) -> float:
        """How much an evaluation must lower `best` to beat it."""
        return self.min_delta + (self.min_gain * abs(best) if math.isfinite(best) else 0.0)

    def lr_at(self, step: int) -> float:
        if self.warmup is None:
            return self.lr
        return self.lr * min(1.0, step / max(self.warmup, 1)) * 0.5 * (1 + math.cos(math.pi * step / self.steps))


@dataclass
class MaskTrainConfig:
    """The schedule of a network trained on corpus pairs against a true mask (S, V); each trainer's
    config derives from it and sets its own defaults."""

    steps: int = 2000
    batch: int = 8
    lr: float = 2e-3
    warmup: int = 100  # linear learning-rate warm-up steps, then cosine decay to 0
    object_weight: float = 2.0  # a missed object pixel or cell costs this many excess ones
    ema_decay: float = 0.995
    eval_every: int = 250
    seed: int = 0

    def plan(self) -> FitPlan:
        return FitPlan(self.steps, self.lr, self.eval_every, warmup=self.warmup, ema_decay=self.ema_decay)


@dataclass
class FitState:
    """Everything besides the tensors that decides how a run goes on; `curve` holds one entry per
    record: the step, the mean training loss since the last record and the evaluation (if any)."""

    step: int = 0
    loss_sum: float = 0.0
    loss_n: int = 0
    curve: dict[str, list] = field(default_factory=lambda: {"step": [], "loss": [], "val": []})
    bar: float = math.inf  # what the run had to beat (see `fit`)
    best: float = math.inf
    bad_evals: int = 0
    stopped_at: int | None = None
    seconds: float = 0.0

    @property
    def finished(self) -> bool:
        return self.stopped_at is not None

    def summary(self) -> dict[str, Any]:
        """The curve with the run's bar, best evaluation, last step and seconds (for curves.json
        and provenance files)."""
        finite = lambda x: x if math.isfinite(x) else None  # noqa: E731 (JSON has no inf)
        return {
            **self.curve,
            "bar": finite(self.bar),
            "best": finite(self.best),
            "stopped_at": self.stopped_at,
            "seconds": round(self.seconds, 1),
        }


class LoopCheckpoint(Protocol):
    """What the loop needs of a checkpoint (`wgs.resume.Checkpointer` is one)."""

    def load(self) -> dict[str, Any] | None: ...
    def due(self) -> bool: ...
    def save(self, state: dict[str, Any]) -> None: ...


Evaluation = float | dict[str, float]
M = TypeVar("M", bound=torch.nn.Module)


def scalar(evaluation: Evaluation) -> float:
    """The number to minimise where the evaluation is one number (`fit`'s monitor)."""
    if isinstance(evaluation, dict):
        raise TypeError("a scalar evaluation was expected")
    return evaluation


def fit(
    model: M,
    opt: torch.optim.Optimizer,
    batch_loss: Callable[[int], torch.Tensor],
    plan: FitPlan,
    name: str,
    *,
    gen: torch.Generator | None = None,
    evaluate: Callable[[M], Evaluation] | None = None,
    monitor: Callable[[Evaluation], float] | None = None,
    bar: float = math.inf,
    checkpoint: LoopCheckpoint | None = None,
    on_record: Callable[[FitState], None] | None = None,
    after_step: Callable[[int, Callable[[], dict[str, Any]]], None] | None = None,
) -> tuple[M, FitState]:
    """Train `model` with `opt` for `plan.steps` steps of `batch_loss(step)`.

    evaluate(module) runs every `plan.eval_every` steps on the EMA (when `plan.ema_decay` is set) or
    on the model; monitor(evaluation) is the number to minimise for the best state and patience, and
    `bar` the number to beat from the start (for example no repair at all, or the starting weights:
    their state is the best until something beats it). `checkpoint` is saved at records when due and
    at the end, and continued from when it loads. `after_step(step, snapshot)` runs after each step
    (for a Ctrl-C check). Returns the trained module (EMA or model, best state when `keep_best`)
    and the loop's state."""
    ema = copy.deepcopy(model).eval() if plan.ema_decay is not None else None
    judged = ema if ema is not None else model
    st = FitState(bar=bar, best=bar)
    best_state = copy.deepcopy(judged.state_dict())
    t0 = time.perf_counter()

    def snapshot() -> dict[str, Any]:
        return {
            "model": model.state_dict(),
            "ema": None if ema is None else ema.state_dict(),
            "opt": opt.state_dict(),
            "generator": None if gen is None else gen.get_state(),
            "rng": torch.get_rng_state(),
            "best_state": best_state,
            "loop": {**asdict(st), "seconds": st.seconds + time.perf_counter() - t0},
        }

    if checkpoint is not None and (saved := checkpoint.load()) is not None:
        if "loop" not in saved:
            raise WgsError(f"{name}: the resume checkpoint is of another wgs version; rerun without --resume")
        model.load_state_dict(saved["model"])
        if ema is not None:
            ema.load_state_dict(saved["ema"])
        opt.load_state_dict(saved["opt"])
        if gen is not None:
            gen.set_state(saved["generator"])
        torch.set_rng_state(saved["rng"])
        best_state = saved["best_state"]
        st = FitState(**saved["loop"])
    model.train()
    for step in range(st.step + 1, plan.steps + 1):
        if st.finished:
            break
        for g in opt.param_groups:
            g["lr"] = plan.lr_at(step)
        loss = batch_loss(step)
        st.loss_sum += clipped_step(opt, model, loss, name, step, ema, plan.ema_decay or 0.0, plan.max_norm)
        st.loss_n += 1
        st.step = step
        if step % plan.eval_every == 0 or step == plan.steps:
            record(st, judged, evaluate, step)
            judged_val = monitor(st.curve["val"][-1]) if st.curve["val"] and monitor is not None else None
            if judged_val is not None and judged_val < st.best - plan.margin(st.best):
                st.best, st.bad_evals, best_state = judged_val, 0, copy.deepcopy(judged.state_dict())
            elif judged_val is not None:
                st.bad_evals += 1
                if plan.patience is not None and st.bad_evals >= plan.patience:
                    st.stopped_at = step
            if step == plan.steps and st.stopped_at is None:
                st.stopped_at = step
            if checkpoint is not None and (st.finished or checkpoint.due()):
                checkpoint.save(snapshot())
            if on_record is not None:
                on_record(st)
        if after_step is not None and not st.finished:
            after_step(step, snapshot)
    if plan.steps == 0:  # nothing to train: the starting weights are the result
        st.stopped_at = 0
    st.seconds += time.perf_counter() - t0
    if plan.keep_best:
        judged.load_state_dict(best_state)
    return judged.eval(), st


def record(st: FitState, judged: M, evaluate: Callable[[M], Evaluation] | None, step: int) -> None:
    """One curve entry: the step, the mean loss since the last entry, and the evaluation."""
    st.curve["step"].append(step)
    st.curve["loss"].append(st.loss_sum / max(st.loss_n, 1))
    st.loss_sum, st.loss_n = 0.0, 0
    if evaluate is not None:
        was_training = judged.training
        judged.eval()
        with torch.no_grad():
            st.curve["val"].append(evaluate(judged))
        judged.train(was_training)
