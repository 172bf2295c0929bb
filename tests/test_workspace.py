"""Workspace contract: atomic writes, lock, staging swap, freshness."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from wgs.errors import WorkspaceLocked
from wgs.io import atomic_path, atomic_write_bytes
from wgs.workspace import Workspace


def test_atomic_write_replaces(tmp_path):
    p = tmp_path / "f.txt"
    atomic_write_bytes(p, b"one")
    atomic_write_bytes(p, b"two")
    assert p.read_bytes() == b"two"
    assert [x.name for x in tmp_path.iterdir()] == ["f.txt"]


def test_failed_write_keeps_old(tmp_path):
    p = tmp_path / "f.txt"
    atomic_write_bytes(p, b"good")
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("crash midway")
    assert p.read_bytes() == b"good"
    assert [x.name for x in tmp_path.iterdir()] == ["f.txt"]


def test_killed_write_keeps_old(tmp_path):
    """A process SIGKILLed in the middle of a write leaves the previous file intact."""
    p = tmp_path / "big.bin"
    atomic_write_bytes(p, b"old")
    code = textwrap.dedent(f"""
        import sys, time
        from wgs.io import atomic_path
        with atomic_path({str(p)!r}) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"x" * 1000)
                fh.flush()
                print("writing", flush=True)
                time.sleep(30)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"writing"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert p.read_bytes() == b"old"


def test_lock_refuses_second_holder(tmp_path):
    ws = Workspace(tmp_path)
    code = textwrap.dedent(f"""
        import time
        from wgs.workspace import Workspace
        with Workspace({str(tmp_path)!r}).lock():
            print("locked", flush=True)
            time.sleep(30)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline().strip() == b"locked"
        with pytest.raises(WorkspaceLocked, match=f"pid {proc.pid}"), ws.lock():
            pass
    finally:
        proc.kill()
        proc.wait()
    # the holder died without releasing: its stale lock is taken over
    with ws.lock():
        assert json.loads((tmp_path / ".wgs.lock").read_text())["pid"] == os.getpid()
    assert not (tmp_path / ".wgs.lock").exists()


def test_stage_run_swaps_only_on_success(tmp_path):
    ws = Workspace(tmp_path)
    with ws.lock():
        with ws.stage_run("prepare", {"a": 1}, "fp1") as run:
            run.path("x.txt").write_text("first")
        assert ws.status("prepare", "fp1") == "fresh"
        with pytest.raises(RuntimeError), ws.stage_run("prepare", {"a": 2}, "fp2") as run:
            run.path("x.txt").write_text("second, half done")
            raise RuntimeError("stage failed")
    assert (ws.stage_dir("prepare") / "x.txt").read_text() == "first"
    assert ws.manifest("prepare")["fingerprint"] == "fp1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_fresh_and_stale(tmp_path):
    ws = Workspace(tmp_path)
    with ws.lock():
        fp_scene = ws.stage_fingerprint("prepare", {"v": 1})
        with ws.stage_run("prepare", {"v": 1}, fp_scene):
            pass
        fp_coarse = ws.stage_fingerprint("coarse", {"it": 10})
        with ws.stage_run("coarse", {"it": 10}, fp_coarse):
            pass
        assert ws.status("coarse", fp_coarse) == "fresh"
        assert ws.status("coarse", ws.stage_fingerprint("coarse", {"it": 11})) == "stale"  # config changed
        with ws.stage_run("prepare", {"v": 2}, ws.stage_fingerprint("prepare", {"v": 2})):
            pass
        assert ws.status("coarse") == "stale"  # upstream changed
        assert ws.status("fine") == "missing"


def test_interrupted_swap_is_recovered(tmp_path):
    ws = Workspace(tmp_path)
    with ws.lock(), ws.stage_run("prepare", {}, "fp") as run:
        run.path("x.txt").write_text("good")
    # simulate a crash between the two renames of a swap
    (tmp_path / "scene").rename(tmp_path / ".scene.old-123")
    (tmp_path / ".scene.tmp-123").mkdir()
    with ws.lock():
        pass
    assert (tmp_path / "scene" / "x.txt").read_text() == "good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_manifest_records_time_and_memory(tmp_path):
    ws = Workspace(tmp_path)
    with ws.lock(), ws.stage_run("prepare", {"k": 1}, "fp"):
        time.sleep(0.01)
    m = ws.manifest("prepare")
    assert m["wall_time_s"] >= 0.01 and m["peak_memory_mb"] > 0 and m["config"] == {"k": 1}
