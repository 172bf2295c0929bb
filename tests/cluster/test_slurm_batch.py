"""`wgs batch --executor slurm` on a real single-node Slurm (`local_slurm.LocalSlurm`): a job array
over three tiny scenes with one broken, and a job stopped at its time limit, requeued and resumed to
the model of an uninterrupted run. `make test-cluster` runs this (as root it installs Slurm from
Debian's packages when absent); `make test` leaves it out (tests/conftest.py)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import TINY_ONE_MODEL, make_scene
from local_slurm import DAEMONS, LocalSlurm, children

from wgs.workspace import Workspace

# the time-limit scene: a coarse stage long enough on one core that the time limit's signal (45-75 s
# into the job) finds it training, and that it still trains when requeued after it resumed, on a
# fast CPU too (5000 iterations took about 100 s on one core of a slow 2-core CPU; on a faster one
# the requeue, 5 s after the stage resumed, found it in a later stage); all its iterations, as
# TINY's: the held-out stopping rule would end it long before
LONG_COARSE = TINY_ONE_MODEL.replace(
    "iterations = 30\nrefine_start = 10\nrefine_every = 10\ninit_points = 800\nhull_resolution = 32\nensemble = 1",
    "iterations = 12000\nrefine_start = 10\nrefine_every = 100\ninit_points = 800\nhull_resolution = 32\nensemble = 1",
    1,
)
assert LONG_COARSE != TINY_ONE_MODEL and 'stop = "iterations"' in LONG_COARSE


@pytest.fixture(scope="module")
def cluster():
    with LocalSlurm() as slurm:
        yield slurm


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    base = tmp_path_factory.mktemp("cluster")
    for i, name in enumerate(["apple", "broken", "cube"]):
        make_scene(base / "data" / name, seed=10 + i, size=48, n_train=4, n_test=3)
    make_scene(base / "data" / "long" / "slow", seed=13, size=64, n_train=4, n_test=3)
    (base / "data" / "broken" / "transforms_train.json").write_text("{ not json")
    (base / "tiny.toml").write_text(TINY_ONE_MODEL)
    (base / "long.toml").write_text(LONG_COARSE)
    (base / "three.txt").write_text("data/apple\ndata/broken\ndata/cube\n")
    (base / "slow.txt").write_text("data/long/slow\n")
    return base


@pytest.fixture(autouse=True)
def no_batch_left(cluster):
    """A failed test leaves no `wgs batch` running against the cluster."""
    yield
    for pid in cluster.job_processes():
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def batch(cluster: LocalSlurm, base: Path, config: str, scene_list: str, root: Path, *extra: str) -> subprocess.Popen:
    """`wgs batch --executor slurm` against the local cluster, in the background (one thread per job,
    the same in every run, so that models compare bit for bit)."""
    cmd = [sys.executable, "-m", "wgs", "--config", str(base / config), "batch", str(base / scene_list)]
    cmd += ["-o", str(root), "--executor", "slurm", "--cluster", "slurm", "--cpus", "1", "--mem-gb", "3", *extra]
    env = {**cluster.env, "WGS_THREADS": "1"}
    return subprocess.Popen(cmd, cwd=base, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, timeout: float = 400) -> tuple[int, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out + err


def jobs(cluster: LocalSlurm) -> list[dict[str, str]]:
    """`scontrol show job`: one dict per job (JobId, JobState, Restarts, Reason, ...)."""
    res = cluster.run("scontrol", "-o", "show", "job", check=False)
    lines = [line for line in res.stdout.splitlines() if "JobId=" in line]
    return [dict(t.split("=", 1) for t in line.split() if "=" in t) for line in lines]


def submitted_id(root: Path, proc: subprocess.Popen, timeout: float = 60) -> str:
    """The first job id the batch `proc` submitted (from its logs folder)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, finish(proc)[1]
        logs = root / "_batch" / "logs"
        found = sorted(p.name for p in logs.iterdir() if p.is_dir() and p.name[0].isdigit()) if logs.is_dir() else []
        if found:
            return found[0].split("_")[0]
        time.sleep(0.5)
    raise AssertionError(f"no job submitted under {root}")


def test_array_of_three_scenes_one_broken(cluster, scenes, tmp_path):
    root = tmp_path / "three"
    before = len(cluster.completions())
    code, output = finish(batch(cluster, scenes, "tiny.toml", "three.txt", root))
    assert code == 1, output  # a scene failed
    summary = json.loads((root / "_batch" / "summary.json").read_text())
    status = {r["scene"]: r["status"] for r in summary["scenes"]}
    assert status == {"apple": "done", "broken": "failed", "cube": "done"}, output
    broken = next(r for r in summary["scenes"] if r["scene"] == "broken")
    assert broken["error"].startswith("error:") and "transforms_train.json" in broken["error"]
    for name in ("apple", "cube"):
        assert Workspace(root / name).output("eval", "results").is_file()
    assert "submitted 3 job(s) to slurm" in output
    # Slurm's own record (sacct): three array elements, each ended on its own (the broken scene's
    # failure is the batch's, not the job's)
    rows = cluster.completions()[before:]
    assert [r["name"] for r in rows] == ["wgs-batch"] * 3, rows
    assert all(r["state"] == "COMPLETED" and r["exitcode"] == "0:0" for r in rows), rows


def requeued_and_started(cluster: LocalSlurm, restarts: int, proc: subprocess.Popen, timeout: float = 240) -> str:
    """Wait until a job is pending after its `restarts`-th requeue; Slurm holds it about two
    minutes (Reason=BeginTime): start it now, with the time to finish, as one would raise a limit
    that proved too short. Returns its job id."""
    end = time.monotonic() + timeout
    while True:
        found = [j for j in jobs(cluster) if j.get("Restarts") == str(restarts) and j.get("JobState") == "PENDING"]
        if found:
            break
        assert time.monotonic() < end, "no job was requeued:\n" + cluster_state(cluster)
        assert proc.poll() is None, finish(proc)[1]
        time.sleep(1)
    job = found[0]["JobId"]
    # slurmd refuses a credential issued in the same second as the one its ended run revoked (whole
    # seconds compared), and Slurm then holds the job ("launch failed requeued held") for good
    time.sleep(2)
    cluster.run("scontrol", "update", f"JobId={job}", "TimeLimit=20", "StartTime=now", check=True)
    return job


def cluster_state(cluster: LocalSlurm) -> str:
    """Each job's state, reason and restarts, and the tail of slurmctld's log: why a job did not run."""
    keys = ("JobId", "JobState", "Reason", "Restarts", "StartTime")
    rows = [" ".join(f"{k}={j.get(k)}" for k in keys) for j in jobs(cluster)]
    ctld = (cluster.dir / "slurmctld.log").read_text(errors="replace")[-2000:]
    return "\n".join(rows) + "\n--- slurmctld.log\n" + ctld


def test_a_job_at_its_time_limit_then_preempted_resumes_to_the_same_model(cluster, scenes, tmp_path):
    reference, limited = tmp_path / "reference", tmp_path / "limited"
    before = len(cluster.completions())
    # a 2-minute limit, signalled 45 s before it: slurmctld looks every 30 s and signals a job whose
    # end is within the warning plus that, so the signal comes 45-75 s into the job, in its coarse stage
    lim = batch(cluster, scenes, "long.toml", "slow.txt", limited, "--time-min", "2", "--signal-s", "45")
    submitted_id(limited, lim)
    # the uninterrupted run, beside the limited one (one core each)
    ref = batch(cluster, scenes, "long.toml", "slow.txt", reference, "--time-min", "20")
    job = requeued_and_started(cluster, 1, lim)
    # then preempted while its coarse stage trains again: `scontrol requeue` (SIGTERM)
    log_file = limited / "_batch" / "logs" / "slow.log"
    # a scheduler cycle to start it, then the process's start (over 120 s in CI once); where it does
    # not start, the jobs' states and slurmctld's log are in the message
    end = time.monotonic() + 420
    while "coarse: resuming from the saved state" not in log_file.read_text():
        assert time.monotonic() < end and lim.poll() is None, cluster_state(cluster) + log_file.read_text()[-1500:]
        time.sleep(0.5)
    time.sleep(2)  # into its training loop, where SIGTERM saves the state
    cluster.run("scontrol", "requeue", job, check=True)
    assert requeued_and_started(cluster, 2, lim) == job
    code, output = finish(lim)
    assert code == 0, output
    code_ref, output_ref = finish(ref)
    assert code_ref == 0, output_ref
    ws_ref, ws_lim = Workspace(reference / "slow"), Workspace(limited / "slow")
    for stage in ("coarse", "fine"):
        a, b = ws_ref.output(stage, "ply"), ws_lim.output(stage, "ply")
        assert a.read_bytes() == b.read_bytes(), f"{stage} model differs after the requeues"
    # each stopped run saved the coarse model's state and the requeued one went on from it
    log = log_file.read_text()
    assert "(SIGUSR2); its state is saved" in log and "(SIGTERM); its state is saved" in log, log[-4000:]
    assert log.count("coarse: resuming from the saved state") == 2, log[-4000:]
    # Slurm's record (sacct): the job ended twice as requeued (recorded PENDING), then COMPLETED
    states = [r["state"] for r in cluster.completions()[before:] if r["jobid"] == job]
    assert states == ["PENDING", "PENDING", "COMPLETED"], cluster.completions()[before:]


def test_a_cluster_stopped_with_a_job_running_leaves_no_process(tmp_path):
    with LocalSlurm() as slurm:
        assert slurm.node_state() == "idle"
        slurm.run("sbatch", "-o", str(tmp_path / "job.out"), "--wrap", "sleep 600")
        end = time.monotonic() + 30
        while "RUNNING" not in {j.get("JobState") for j in jobs(slurm)}:
            assert time.monotonic() < end, jobs(slurm)
            time.sleep(0.5)
        folder = str(slurm.dir)
    left = subprocess.run(["pgrep", "-f", folder], capture_output=True, text=True).stdout.split()
    assert not left, subprocess.run(["ps", "-fp", ",".join(left)], capture_output=True, text=True).stdout
    assert not slurm.job_processes()
    assert not {pid: c for pid, c in children().items() if c[0] in DAEMONS or c[1] == "Z"}, children()
