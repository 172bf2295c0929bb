"""Thread discipline (issue 13): the settings that keep two wgs processes from spinning against
each other stay in place, and the thread count follows --threads / WGS_THREADS / the cores."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from wgs import threads
from wgs.errors import WgsError

PROBE = ("import json, wgs.threads as t, numba, numpy as np\n"
         "@numba.njit(parallel=True)\n"
         "def f(x):\n"
         "    s = 0.0\n"
         "    for i in numba.prange(x.shape[0]):\n"
         "        s += x[i]\n"
         "    return s\n"
         "t.configure(None); f(np.ones(100)); print(json.dumps(t.describe()))")


def probe(env: dict[str, str]) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in (*threads.COUNT_VARS, threads.ENV)}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True, text=True,
                         check=True)
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
    out = subprocess.run([sys.executable, "-m", "wgs", "--threads", "1", "-w", str(ws), "info"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "threads: torch 1, numba 1" in out.stdout and "fixed" in out.stdout
