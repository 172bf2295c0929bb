"""Thread discipline: the settings that keep two wgs processes from spinning against
each other stay in place, and the thread count follows --threads / WGS_THREADS / the cores."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from wgs import threads
from wgs.errors import WgsError

PROBE = (
    "import json, wgs.threads as t, numba, numpy as np\n"
    "@numba.njit(parallel=True)\n"
    "def f(x):\n"
    "    s = 0.0\n"
    "    for i in numba.prange(x.shape[0]):\n"
    "        s += x[i]\n"
    "    return s\n"
    "t.configure(None); f(np.ones(100)); print(json.dumps(t.describe()))"
)


def probe(env: dict[str, str]) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in (*threads.COUNT_VARS, threads.ENV)}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_runtime_settings_in_a_fresh_process():
    d = probe({})
    # a thread count that adapts to other processes (two wgs side by side: 11x slower without)
    assert d["adaptive"]
    assert d["OMP_NUM_THREADS"] == str(threads.available_cores())
    assert d["torch_threads"] == d["numba_threads"] == threads.available_cores()


def test_wgs_threads_env_sets_both_pools_and_fixes_the_count():
    d = probe({"WGS_THREADS": "1"})
    assert d["torch_threads"] == 1 and d["numba_threads"] == 1
    assert not d["adaptive"]


def test_user_exports_win():
    d = probe({"OMP_NUM_THREADS": "1"})
    assert d["OMP_NUM_THREADS"] == "1"


class FakeClock:
    """cpu_sample stand-in: each call advances 1 s; `others` / `mine` cores busy during it."""

    def __init__(self):
        self.t, self.busy, self.mine, self.others, self.own = 0.0, 0.0, 0.0, 0.0, 1.0

    def __call__(self):
        self.t += 1.0
        self.busy += self.others + self.own
        self.mine += self.own
        return self.t, self.busy, self.mine


def test_governor_shrinks_while_others_work_and_grows_back(monkeypatch):
    clock = FakeClock()
    applied = []
    monkeypatch.setattr(threads.time, "monotonic", lambda: clock.t + 10.0)  # every tick is due
    g = threads.Governor(4, sample=clock, apply=applied.append)
    assert g.tick() == 4  # first sample: nothing to compare yet
    clock.others = 0.2  # background noise: keep every thread
    assert g.tick() == 4
    clock.others = 2.0  # another job keeps two cores busy
    assert g.tick() == 2
    clock.others = 7.0  # more than all cores: still one thread
    assert g.tick() == 1
    clock.others = 0.0
    assert g.tick() == 4
    assert applied == [2, 1, 4]


def test_governor_fixed_or_single_core_never_samples():
    def boom():
        raise AssertionError("sampled")

    assert threads.Governor(4, adaptive=False, sample=boom).tick() == 4
    assert threads.Governor(1, sample=boom).tick() == 1


def test_thread_count_order(monkeypatch):
    monkeypatch.setenv("WGS_THREADS", "3")
    assert threads.thread_count(5) == 5
    assert threads.thread_count() == 3
    monkeypatch.delenv("WGS_THREADS")
    assert threads.thread_count() == threads.available_cores() >= 1


@pytest.mark.parametrize("value", ["0", "two"])
def test_bad_wgs_threads(monkeypatch, value):
    monkeypatch.setenv("WGS_THREADS", value)
    with pytest.raises(WgsError, match="WGS_THREADS|at least 1"):
        threads.thread_count()


def test_cgroup_quota(tmp_path):
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert threads.cgroup_quota(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert threads.cgroup_quota(tmp_path) is None
    assert threads.cgroup_quota(tmp_path / "absent") is None


def test_cli_threads_option(tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    out = subprocess.run(
        [sys.executable, "-m", "wgs", "--threads", "1", "-w", str(ws), "info"], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert "threads: torch 1, numba 1" in out.stdout and "fixed" in out.stdout


def test_jobs_in_processes_come_back_by_index_with_one_thread_each():
    jobs = [(f"{i}",) for i in range(5)]
    out = dict(threads.map_in_processes(int, jobs, 2))
    assert out == {i: i for i in range(5)}
    # the children run one thread each, and the parent's environment is left as it was
    before = {k: os.environ.get(k) for k in (threads.ENV, *threads.COUNT_VARS)}
    code = "import torch; print(torch.get_num_threads())"
    got = dict(threads.map_in_processes(subprocess.check_output, [([sys.executable, "-c", code],)] * 2, 2))
    assert {int(v) for v in got.values()} == {1}
    assert {k: os.environ.get(k) for k in before} == before


def test_jobs_start_in_the_order_given_as_processes_free():
    """3 jobs on 2 processes, started in the order 2, 1, 0: job 0 waits until one of the others
    has slept its second out (a causal bound: it holds however slowly the processes start)."""
    code = "import time; print(time.monotonic()); time.sleep(1.0)"
    jobs = [([sys.executable, "-c", code],)] * 3
    started = {i: float(v) for i, v in threads.map_in_processes(subprocess.check_output, jobs, 2, order=[2, 1, 0])}
    assert started[0] > min(started[1], started[2]) + 0.95
    with pytest.raises(ValueError, match="each of the 3 jobs' indices once"):
        list(threads.map_in_processes(int, [("1",)] * 3, 2, order=[0, 0, 1]))


def test_in_process_when_one_worker_and_a_child_error_reaches_the_parent():
    assert list(threads.map_in_processes(int, [("7",), ("8",)], 1)) == [(0, 7), (1, 8)]
    with pytest.raises(ValueError, match="invalid literal"):
        dict(threads.map_in_processes(int, [("1",), ("x",)], 2))


def proc_stat(pid: int) -> list[str] | None:
    """state, ppid, ... of a live process (None when gone or a zombie)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] in ("Z", "X") else fields


def children_of(pid: int) -> list[int]:
    return [int(p) for p in os.listdir("/proc") if p.isdigit() and (st := proc_stat(int(p))) and int(st[1]) == pid]


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads children from /proc")
def test_children_leave_when_their_parent_is_killed():
    import signal
    import time

    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import time, wgs.threads as t\n"
            "print('go', flush=True)\n"
            "dict(t.map_in_processes(time.sleep, [(60,), (60,)], 2))",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert parent.stdout.readline().strip() == "go"
    deadline = time.monotonic() + 60
    while len(kids := children_of(parent.pid)) < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert len(kids) >= 2
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 20
    while any(proc_stat(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(proc_stat(k) for k in kids), "the pool's children outlived their killed parent"


DEFERRING_JOB = """
import time
from pathlib import Path

from wgs.resume import deferred_stop, stop_requested


def job(marker, seconds):
    with deferred_stop():  # as a training loop: a stop signal ends it at the end of an iteration
        Path(marker).touch()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            if stop_requested():
                raise RuntimeError("stopped at the end of an iteration")
            time.sleep(0.05)
"""


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads children from /proc")
def test_sigterm_to_the_parent_ends_it_and_its_children_inside_their_loops(tmp_path):
    """`kill PID` of a run whose models train side by side: the parent stops (`Stopped`) and its
    pool's SIGTERM ends the children at once, though their loops defer stop signals; deferred, a
    child ended its loop and then waited for work, and the parent waited for it."""
    import signal
    import time

    (tmp_path / "deferring.py").write_text(DEFERRING_JOB)
    marks = [tmp_path / "a", tmp_path / "b"]
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import sys; sys.path.insert(0, {str(tmp_path)!r})\n"
            "import deferring, wgs.threads as t\n"
            "from wgs.resume import install_stop_handlers\n"
            "install_stop_handlers()\n"
            f"dict(t.map_in_processes(deferring.job, [({str(marks[0])!r}, 60), ({str(marks[1])!r}, 60)], 2))",
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not all(m.exists() for m in marks) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert all(m.exists() for m in marks), "the children never started their loops"
    kids = children_of(parent.pid)
    parent.send_signal(signal.SIGTERM)
    try:
        parent.wait(timeout=30)
    except subprocess.TimeoutExpired:
        parent.kill()
        raise AssertionError("the parent did not end within 30 s of SIGTERM") from None
    assert parent.returncode != 0
    deadline = time.monotonic() + 20
    while any(proc_stat(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(proc_stat(k) for k in kids), "the pool's children outlived their stopped parent"
