"""Thread discipline: the one place that decides how many threads torch, numba and BLAS use.

Measured on a 2-core machine (`python -m tools.bench contention`, 600 coarse iterations on lego):
with a fixed thread count one run takes 56 s and two runs started together 618 s each (11x),
because OpenMP threads spin while they wait and two processes' spinning threads steal each
other's cores. A passive wait policy fixes the pair (89 s) but costs 25% alone (71 s), and one
thread each takes 85 s either way. So wgs keeps spinning pools while it has the cores to itself
and shrinks them while other processes keep cores busy (`adapt`, called by the training loops):
55 s alone, 86 s each for two (1.6x). A fixed count (`--threads N`, `WGS_THREADS`) turns this
off; bit-identical reruns need one, since sums depend on the thread count. numba keeps its own
threading layer choice (omp here: 10% faster than workqueue alone, the same in pairs).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

ENV = "WGS_THREADS"
# thread counts read once when a runtime starts: set (unless exported) before torch / numba start
COUNT_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")

T = TypeVar("T")


def cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """CPUs allowed by a cgroup v2 (`cpu.max`) or v1 (`cpu.cfs_quota_us`) quota; None without one."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period_us = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return quota_us / period_us if quota_us > 0 and period_us > 0 else None
    except (OSError, ValueError):
        return None


def available_cores() -> int:
    """Cores this process may run on: its CPU affinity, capped by a cgroup quota."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    quota = cgroup_quota()
    if quota is not None:
        n = min(n, max(1, math.ceil(quota)))
    return max(1, n)


def thread_count(requested: int | None = None) -> int:
    """`requested` (--threads), else WGS_THREADS, else the available cores."""
    if requested is None and os.environ.get(ENV, "").strip():
        try:
            requested = int(os.environ[ENV])
        except ValueError:
            from .errors import WgsError

            raise WgsError(f"{ENV} must be a positive integer, got {os.environ[ENV]!r}") from None
    if requested is not None and requested < 1:
        from .errors import WgsError

        raise WgsError(f"thread count must be at least 1, got {requested}")
    return requested if requested is not None else available_cores()


def set_runtime_defaults(env: MutableMapping[str, str] | None = None) -> None:
    """Thread counts for runtimes that read them only when they start (user exports win)."""
    if env is None:
        env = os.environ
    try:
        n = str(thread_count())
    except Exception:  # a bad WGS_THREADS: `configure` reports it as one error line
        return
    for key in COUNT_VARS:
        env.setdefault(key, n)


def cpu_sample() -> tuple[float, float, float] | None:
    """(wall s, CPU s used by the whole machine, CPU s used by this process); None off Linux."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, ValueError, IndexError):
        return None
    tick = os.sysconf("SC_CLK_TCK")
    busy = sum(v) - v[3] - v[4]  # all but idle and iowait
    return time.monotonic(), busy / tick, (int(fields[11]) + int(fields[12])) / tick


@dataclass
class Governor:
    """Thread count that follows the cores other processes leave free (see the module docstring)."""

    cores: int
    adaptive: bool = True
    every_s: float = 1.0
    sample: Callable[[], tuple[float, float, float] | None] = cpu_sample
    apply: Callable[[int], None] | None = None
    current: int = 0
    _last: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        self.current = self.cores

    def tick(self) -> int:
        """Cheap unless `every_s` passed: then measure others' CPU use and set the thread count."""
        if not self.adaptive or self.cores <= 1:
            return self.current
        if self._last is not None and time.monotonic() - self._last[0] < self.every_s:
            return self.current
        now = self.sample()
        if now is None:
            self.adaptive = False
            return self.current
        last, self._last = self._last, now
        if last is None or now[0] <= last[0]:
            return self.current
        others = max(0.0, (now[1] - last[1]) - (now[2] - last[2])) / (now[0] - last[0])
        target = max(1, self.cores - int(others + 0.5))
        if target != self.current:
            self.current = target
            if self.apply is not None:
                self.apply(target)
        return self.current


_governor: Governor | None = None


def set_pools(n: int) -> None:
    import torch

    torch.set_num_threads(n)
    try:
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    except (ImportError, ValueError):
        pass


def configure(threads: int | None = None) -> int:
    """Set torch's and numba's thread counts now; adaptive unless a count was given (here or in
    WGS_THREADS). Returns the count."""
    global _governor
    fixed = threads is not None or bool(os.environ.get(ENV, "").strip())
    n = thread_count(threads)
    set_pools(n)
    _governor = Governor(n, adaptive=not fixed, apply=set_pools)
    return n


def adapt() -> int:
    """Call from the main thread of long loops (torch's thread count is per calling thread)."""
    return _governor.tick() if _governor is not None else 0


def configured_count() -> int:
    """The thread count this process was configured with (`configure`), else `thread_count()`."""
    return _governor.cores if _governor is not None else thread_count()


# A spawned process takes about 5 s to start (torch, numba's cached kernels): worth it from about
# a lego member's quarter (1500 iterations x 200 x 200 px = 6e7 pixel-iterations, 48 s here).
SIDE_BY_SIDE_MIN_WORK = 1.5e7


def side_by_side(models: int, iterations: int, pixels: int, on_cpu: bool) -> int:
    """How many of `models` models train at once: on the CPU one per thread this process may use,
    each in a one-thread process (1.5x the throughput of one model on both cores), when a model's
    work (`iterations` x `pixels` per view) pays for starting a process; else 1."""
    if not on_cpu or iterations * pixels < SIDE_BY_SIDE_MIN_WORK:
        return 1
    return min(configured_count(), models)


def _child_start(parent: int, quiet: bool) -> None:
    """A pool child: one thread, quiet if asked, stopped at once by the pool's SIGTERM
    (`resume.as_pool_child`), and gone when its parent is (a SIGKILLed parent's children would
    otherwise train on, stealing the cores from the rerun)."""
    import threading

    from .progress import set_quiet
    from .resume import as_pool_child

    set_pools(1)
    set_quiet(quiet)
    as_pool_child()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _indexed_call(task: tuple[int, Callable, tuple]) -> tuple[int, object]:
    i, fn, job = task
    return i, fn(*job)


def map_in_processes(
    fn: Callable[..., T], jobs: list[tuple], workers: int, quiet: bool = True, order: list[int] | None = None
) -> Iterator[tuple[int, T]]:
    """(index, fn(*job)) for every job, in the order they finish: here when `workers` <= 1 (with
    this process's threads), else in `workers` spawned processes of one thread each (`quiet`: their
    console output off, since the children's progress bars would interleave), each job started as a
    process frees in `order` (the jobs' indices; default theirs: the longest first ends the batch
    soonest).

    Why processes: on 2 cores two one-thread coarse trainings take 64 s each side by side where
    one with both cores takes 48 s (1.5x the throughput; small tensors leave threads idle).
    `fn` must be importable (module level); its arguments and result travel by pickle."""
    if order is not None and sorted(order) != list(range(len(jobs))):
        raise ValueError(f"map_in_processes: order must hold each of the {len(jobs)} jobs' indices once, got {order}")
    if workers <= 1 or len(jobs) <= 1:
        for i, job in enumerate(jobs):
            yield i, fn(*job)
        return
    import multiprocessing as mp

    saved = {k: os.environ.get(k) for k in (ENV, *COUNT_VARS)}
    os.environ.update({k: "1" for k in saved})  # the children's runtimes read these when they start
    try:
        pool = mp.get_context("spawn").Pool(min(workers, len(jobs)), _child_start, (os.getpid(), quiet))
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    try:
        started = order if order is not None else range(len(jobs))
        yield from pool.imap_unordered(_indexed_call, [(i, fn, jobs[i]) for i in started])
    except BaseException:  # a child's exception (re-raised here), Ctrl-C, or the caller stopping early
        pool.terminate()
        raise
    pool.close()  # not terminate(): the workers exit on their own (pycolmap prints stacks on SIGTERM)
    pool.join()


def describe() -> dict[str, object]:
    """What is in force: for `wgs info`, benchmarks and tests."""
    import numba
    import torch

    layer: str
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel function ran yet
        layer = f"{numba.config.THREADING_LAYER} (not started)"  # type: ignore[attr-defined]
    return {
        "cores": available_cores(),
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "numba_layer": layer,
        "adaptive": bool(_governor and _governor.adaptive),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS"),
    }
