"""Resumable loops: periodic full-state checkpoints and a clean Ctrl-C.

A long loop saves everything that decides its future (parameters, optimiser moments, random
generator states, counters) to `WS/.resume/<stage>/<key>.pt` every `every_s` seconds, atomically.
`wgs --resume ...` loads it and continues; the result is the one of an uninterrupted run with the
same seed, because the same floating-point operations run in the same order.

Ctrl-C inside a loop finishes the current iteration, saves a checkpoint and raises `Interrupted`;
a second Ctrl-C stops at once (the last periodic checkpoint stays).
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from .errors import WgsError
from .io.checkpoint import UnreadableCheckpoint, read_checkpoint, write_checkpoint


class Interrupted(WgsError):
    """Ctrl-C inside a resumable loop: its state was saved."""


class Checkpointer:
    """Saves and loads one loop's state; `due()` says when the next periodic save is."""

    def __init__(self, path: Path, every_s: float, resume: bool):
        self.path = Path(path)
        self.every_s = every_s
        self.resume = resume
        self._last = time.monotonic()

    def load(self) -> dict[str, Any] | None:
        """The saved state when resuming and one exists, else None (tensors on the CPU)."""
        if not self.resume or not self.path.exists():
            return None
        try:
            return read_checkpoint(self.path)
        except UnreadableCheckpoint as exc:
            raise WgsError(f"cannot read the resume checkpoint ({exc}); "
                           "rerun without --resume to start the stage over", self.path) from None

    def due(self) -> bool:
        return time.monotonic() - self._last >= self.every_s

    def save(self, state: dict[str, Any]) -> None:
        write_checkpoint(self.path, state)
        self._last = time.monotonic()


def rng_state() -> dict[str, Any]:
    """The global torch generators (the strategy's split sampling and model init use them)."""
    out: dict[str, Any] = {"cpu": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        out["cuda"] = torch.cuda.get_rng_state_all()
    return out


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["cpu"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ----------------------------------------------------------------------------- Ctrl-C
_requested = threading.Event()


def stop_requested() -> bool:
    return _requested.is_set()


@contextlib.contextmanager
def deferred_sigint() -> Iterator[None]:
    """Inside the block the first Ctrl-C only sets a flag (see `stop_requested`); the second one
    raises KeyboardInterrupt as usual. Outside the main thread this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        if _requested.is_set():
            raise KeyboardInterrupt
        _requested.set()

    previous = signal.signal(signal.SIGINT, handler)
    _requested.clear()
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _requested.clear()


def check_interrupt(what: str, step: int, checkpoint: Checkpointer | None, state: Any) -> None:
    """Call at the end of a loop iteration: on a pending Ctrl-C save `state()` and raise Interrupted."""
    if not stop_requested():
        return
    if checkpoint is not None:
        checkpoint.save(state())
        raise Interrupted(f"{what} stopped after step {step}; its state is saved: rerun the same command "
                          "with `wgs --resume ...` to continue")
    raise Interrupted(f"{what} stopped after step {step}; rerun to start the stage over")
