"""Resumable loops: periodic full-state checkpoints and a clean Ctrl-C.

A long loop saves everything that decides its future (parameters, optimiser moments, random
generator states, counters) to `WS/.resume/<stage>/<key>.pt` every `every_s` seconds, atomically.
`wgs --resume ...` loads it and continues; the result is the one of an uninterrupted run with the
same seed, because the same floating-point operations run in the same order.

A stop signal inside a loop (Ctrl-C's SIGINT, or a scheduler's SIGTERM, SIGUSR1 or SIGUSR2: Slurm
sends one at a job's time limit or preemption, SIGUSR2 where submitit asked for it) finishes the
current iteration, saves a checkpoint and raises `Interrupted`; a second one stops at once (the
last periodic checkpoint stays). Outside a loop SIGTERM, SIGUSR1 and SIGUSR2 stop at once as Ctrl-C
does (`Stopped`). The CLI exits with 128 + the signal's number, as the shell expects (130, 143, 138,
140).
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
    """A stop signal inside a resumable loop: its state was saved. `signum`: the signal."""

    def __init__(self, message: str, signum: int = signal.SIGINT):
        super().__init__(message)
        self.signum = int(signum)


class Stopped(KeyboardInterrupt):
    """SIGTERM, SIGUSR1 or SIGUSR2 outside a resumable loop, or a second stop signal inside one: stop at once."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


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
            raise WgsError(
                f"cannot read the resume checkpoint ({exc}); rerun without --resume to start the stage over", self.path
            ) from None

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


# ----------------------------------------------------------------------------- stop signals
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)
_requested = threading.Event()
_received: list[int] = []  # the first stop signal of the current loop
_installed = False
_pool_child = False  # a process of `threads.map_in_processes` (`as_pool_child`)


def stop_requested() -> bool:
    return _requested.is_set()


def _stop_at_once(signum, frame):  # noqa: ARG001
    raise Stopped(signum)


def install_stop_handlers() -> None:
    """SIGTERM, SIGUSR1 and SIGUSR2 stop like Ctrl-C (`Stopped`), for the rest of the process (the CLI calls
    it; SIGINT keeps Python's KeyboardInterrupt). Outside the main thread this does nothing."""
    global _installed
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in STOP_SIGNALS[1:]:
        signal.signal(sig, _stop_at_once)
    _installed = True


def restore_stop_handlers() -> None:
    """Put our handlers back after a native library installed its own on import (pycolmap's glog
    prints a native stack trace on SIGTERM); nothing where they were never installed."""
    if _installed:
        install_stop_handlers()


def as_pool_child() -> None:
    """In a process of `threads.map_in_processes`: SIGTERM, by which its parent's pool stops it,
    ends it at once, inside `deferred_stop` too. Deferred, it would end the loop and leave the
    process waiting for work that never comes, and the parent's pool waiting for the process."""
    global _pool_child
    _pool_child = True
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@contextlib.contextmanager
def deferred_stop() -> Iterator[None]:
    """Inside the block the first stop signal only sets a flag (see `stop_requested`); the second
    one stops at once (KeyboardInterrupt for SIGINT, `Stopped` for the others). Outside the main
    thread this does nothing; in a pool's process SIGTERM is not deferred (`as_pool_child`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        if _requested.is_set():
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise Stopped(signum)
        _received[:] = [signum]
        _requested.set()

    deferred = [sig for sig in STOP_SIGNALS if not (_pool_child and sig == signal.SIGTERM)]
    previous = {sig: signal.signal(sig, handler) for sig in deferred}
    _requested.clear()
    try:
        yield
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        _requested.clear()


def check_interrupt(what: str, step: int, checkpoint: Checkpointer | None, state: Any) -> None:
    """Call at the end of a loop iteration: on a pending stop signal save `state()` and raise Interrupted."""
    if not stop_requested():
        return
    signum = _received[0] if _received else signal.SIGINT
    name = signal.Signals(signum).name
    if checkpoint is not None:
        checkpoint.save(state())
        raise Interrupted(
            f"{what} stopped after step {step} ({name}); its state is saved: rerun the same command "
            "with `wgs --resume ...` to continue",
            signum,
        )
    raise Interrupted(f"{what} stopped after step {step} ({name}); rerun to start the stage over", signum)
