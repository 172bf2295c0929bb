"""`wgs batch`: the local pool on three tiny scenes (one broken), sharding, the scene list, and the
submitit path through its local executor (no cluster here)."""

import csv
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import click
import pytest
from conftest import TINY_ONE_MODEL, expect_error, make_scene, run_cli

from wgs.batch import SceneTask, read_scene_list, shard, shard_from_env
from wgs.cli import cli
from wgs.cli.batch import all_options_check
from wgs.errors import InputError

pytestmark = pytest.mark.slow  # `pytest -m 'not slow'` for a quick loop; make test runs all


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    base = tmp_path_factory.mktemp("batch")
    for i, name in enumerate(["apple", "broken", "cube"]):
        make_scene(base / "data" / name, seed=10 + i, size=48, n_train=4, n_test=3)
    (base / "data" / "broken" / "transforms_train.json").write_text("{ not json")
    (base / "wgs.toml").write_text(TINY_ONE_MODEL)
    (base / "scenes.txt").write_text("# three objects\ndata/apple --views 4\ndata/broken\n\ndata/cube  # the last\n")
    return base


def batch(base: Path, root: Path, *extra) -> subprocess.CompletedProcess:
    return run_cli(["--config", base / "wgs.toml", "batch", base / "scenes.txt", "-o", root, *extra], base, timeout=600)


def test_local_pool_two_succeed_one_fails_and_a_rerun_skips_the_finished(scenes, tmp_path):
    root = tmp_path / "out"
    proc = batch(scenes, root, "--jobs", "2")
    assert proc.returncode == 1, proc.stderr  # one scene failed
    assert (root / "apple" / "6_eval" / "results.json").is_file()
    assert (root / "cube" / "6_eval" / "results.json").is_file()
    err = (root / "broken" / "error.txt").read_text()
    assert "transforms_train.json" in err and "not valid JSON" in err
    assert not (root / "apple" / "error.txt").exists()
    summary = json.loads((root / "_batch" / "summary.json").read_text())
    status = {r["scene"]: r["status"] for r in summary["scenes"]}
    assert status == {"apple": "done", "broken": "failed", "cube": "done"}
    assert summary["counts"] == {"done": 2, "failed": 1, "not run": 0}
    done = [r for r in summary["scenes"] if r["status"] == "done"]
    for r in done:
        assert math.isfinite(r["psnr"]) and r["total_time_s"] > 0 and set(r["stage_times_s"]) >= {"coarse", "fine"}
    assert summary["mean"]["psnr"] == pytest.approx(sum(r["psnr"] for r in done) / 2)
    rows = list(csv.DictReader((root / "_batch" / "summary.csv").open()))
    assert [r["scene"] for r in rows] == ["apple", "broken", "cube", "mean", "std"]
    assert float(rows[3]["psnr"]) == pytest.approx(summary["mean"]["psnr"])
    assert (root / "_batch" / "logs" / "cube.log").is_file()
    assert "broken" in proc.stdout and "failed" in proc.stdout  # the rich table

    again = batch(scenes, root, "--jobs", "2")
    assert again.returncode == 1
    summary2 = json.loads((root / "_batch" / "summary.json").read_text())
    this_run = {r["scene"]: r.get("this_run") for r in summary2["scenes"]}
    assert this_run == {"apple": "skipped", "broken": "failed", "cube": "skipped"}
    assert "apple: skipped" in again.stderr


def test_shards_cover_every_scene_exactly_once():
    tasks = [SceneTask(f"s{i}", f"/x/s{i}") for i in range(11)]
    for n in (1, 2, 3, 4, 11, 15):
        covered = [t.name for r in range(n) for t in shard(tasks, r, n)]
        assert sorted(covered) == sorted(t.name for t in tasks) and len(covered) == len(tasks)


def test_shard_read_from_slurm_array_variables(monkeypatch):
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "7")
    monkeypatch.setenv("SLURM_ARRAY_TASK_MIN", "5")
    monkeypatch.setenv("SLURM_ARRAY_TASK_COUNT", "4")
    assert shard_from_env(None, None) == (2, 4)
    assert shard_from_env(1, 3) == (1, 3)  # explicit options win
    monkeypatch.delenv("SLURM_ARRAY_TASK_ID")
    assert shard_from_env(None, None) == (0, 1)


def test_sharded_runs_split_the_work(scenes, tmp_path):
    """Two ranks of `wgs batch --summary-only`-free runs: each touches only its own scenes."""
    root = tmp_path / "out"
    proc = batch(scenes, root, "--rank", "1", "--world-size", "2")
    assert proc.returncode == 1  # rank 1 of [apple, broken, cube] is broken
    assert (root / "broken" / "error.txt").is_file()
    assert not (root / "apple").exists() and not (root / "cube").exists()
    summary = json.loads((root / "_batch" / "summary.json").read_text())
    assert summary["counts"] == {"done": 0, "failed": 1, "not run": 2}


def test_scene_list_parsing_and_its_errors(scenes, tmp_path):
    check = all_options_check(cli.commands["all"])
    tasks = read_scene_list(str(scenes / "scenes.txt"), check)
    assert [(t.name, t.options) for t in tasks] == [("apple", ("--views", "4")), ("broken", ()), ("cube", ())]
    assert all(Path(t.scene).is_absolute() for t in tasks)
    globbed = read_scene_list(str(scenes / "data" / "*"), check)
    assert [t.name for t in globbed] == ["apple", "broken", "cube"]
    bad = tmp_path / "bad.txt"
    for text, needle in [
        (f"{scenes}/data/apple --viewz 4\n", "line 1: No such option '--viewz'"),
        (f"{scenes}/data/apple --views four\n", "line 1: Invalid value for '--views'"),
        (f"{scenes}/data/nothere\n", "line 1: scene folder not found"),
        (f"{scenes}/data/apple -w elsewhere\n", "line 1: -w is set by wgs batch"),
        (f"{scenes}/data/apple\n{scenes}/data/apple\n", "two scenes are named 'apple'"),
        ("# nothing\n", "names no scene"),
    ]:
        bad.write_text(text)
        with pytest.raises(InputError, match=re.escape(needle)):
            read_scene_list(str(bad), check)
    expect_error(tmp_path, ["batch", tmp_path / "none*", "-o", tmp_path / "o"], "no scene folder matches")


def test_slurm_path_through_submitit_local_executor(scenes, tmp_path):
    pytest.importorskip("submitit")
    (tmp_path / "one.txt").write_text(f"{scenes}/data/cube\n")
    root = tmp_path / "out"
    proc = run_cli(
        [
            "--config",
            scenes / "wgs.toml",
            "batch",
            tmp_path / "one.txt",
            "-o",
            root,
            "--executor",
            "slurm",
            "--cluster",
            "local",
            "--time-min",
            "10",
            "--cpus",
            "1",
        ],
        tmp_path,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "submitted 1 job(s) to local" in proc.stderr
    assert (root / "cube" / "6_eval" / "results.json").is_file()
    job_logs = [p for p in (root / "_batch" / "logs").iterdir() if p.is_dir() and p.name.isdigit()]  # <job id>/
    assert job_logs and any(p.name.endswith("_result.pkl") for d in job_logs for p in d.iterdir())
    summary = json.loads((root / "_batch" / "summary.json").read_text())
    assert summary["counts"]["done"] == 1


def test_slurm_without_submitit_is_a_clear_error(monkeypatch, scenes, tmp_path):
    import wgs.batch as b

    monkeypatch.setitem(sys.modules, "submitit", None)
    with pytest.raises(b.InputError, match=r"pip install 'wgs\[slurm\]'"):
        opts = b.SlurmOptions(None, None, 120, 0, 4, None, 32, 90, 3)
        b.run_submitit([SceneTask("cube", str(scenes / "data" / "cube"))], tmp_path, [], opts)
    assert isinstance(cli.commands["batch"], click.Command)


def test_a_slurm_job_hands_back_its_call_once_its_stopping_child_has_exited():
    """submitit calls SceneJob.checkpoint from its signal handler: it waits for the `wgs` child
    (which saves and stops on the same signal) and hands back the same call, without the child's
    pid; `make test-cluster` runs the whole path on a real Slurm."""
    pytest.importorskip("submitit")
    import pickle
    import time

    from wgs.batch import SceneJob, exited

    job = SceneJob()
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.5)"])
    job._started(child.pid)
    assert not exited(child.pid)
    t0 = time.monotonic()
    again = job.checkpoint(SceneTask("cube", "/x"), "/root", ["--seed", "0"], False)
    assert time.monotonic() - t0 > 1.0 and exited(child.pid)
    assert child.wait() == 0  # still waitable: its Popen reaps it
    assert isinstance(again.function, SceneJob) and again.function.child is None
    assert again.args == (SceneTask("cube", "/x"), "/root", ["--seed", "0"], False)
    assert pickle.loads(pickle.dumps(job)).child is None
