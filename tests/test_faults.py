"""Faults of the machine: a full disk, a read-only workspace, a second writer. Each gives one clear
line, and the workspace keeps its last good state (no half-written file where a stage reads)."""

import contextlib
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import run_cli

from wgs.workspace import Workspace

# a short coarse stage that still runs the pilots and more than one model: a fault may hit any of them
FAST = "[coarse]\niterations = 60\ninit_points = 800\nhull_resolution = 32\nensemble = 2\n"


@pytest.fixture(scope="module")
def prepared_once(blender_scene, tmp_path_factory) -> Path:
    """`wgs prepare` on the scene, once for the module; tests change copies of it."""
    base = tmp_path_factory.mktemp("faults")
    assert run_cli(["-q", "-w", base / "ws", "prepare", blender_scene], base).returncode == 0
    return base / "ws"


@pytest.fixture
def prepared(prepared_once, tmp_path):
    """A workspace (in tmp_path/ws) with the scene prepared; the config beside it."""
    (tmp_path / "wgs.toml").write_text(FAST)
    shutil.copytree(prepared_once, tmp_path / "ws")
    return tmp_path / "ws"


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    err = proc.stderr.strip()
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


def assert_last_good_state(ws: Path, scene_manifest: str) -> None:
    assert (ws / "scene" / "manifest.json").read_text() == scene_manifest
    assert not (ws / "1_coarse").exists()
    assert Workspace(ws).manifest("coarse") is None
    # no temporary file left where a later stage could read it
    assert not [p for p in ws.rglob("*") if ".tmp-" in p.name and ".resume" not in p.parts]


@contextlib.contextmanager
def tmpfs(path: Path, size: str, *options: str):
    path.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", ",".join([f"size={size}", *options]), "tmpfs", str(path)],
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip()}); the RLIMIT_FSIZE test covers a full disk")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def test_disk_full_on_a_tiny_tmpfs(prepared, tmp_path):
    with tmpfs(tmp_path / "small", "450k") as small:
        ws = small / "ws"
        shutil.copytree(prepared, ws)
        manifest = (ws / "scene" / "manifest.json").read_text()
        proc = run_cli(["-q", "--config", tmp_path / "wgs.toml", "-w", ws, "coarse"], tmp_path)
        assert proc.returncode == 1, proc.stderr
        assert "No space left on device" in one_error_line(proc)
        assert_last_good_state(ws, manifest)


def limit_file_size():
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000))  # writes past 100 kB fail with EFBIG


def test_disk_full_as_a_file_size_limit(prepared, tmp_path):
    manifest = (prepared / "scene" / "manifest.json").read_text()
    proc = subprocess.run(
        [sys.executable, "-m", "wgs", "-q", "--config", str(tmp_path / "wgs.toml"), "-w", str(prepared), "coarse"],
        capture_output=True,
        text=True,
        preexec_fn=limit_file_size,
        timeout=180,
    )
    assert proc.returncode == 1, proc.stderr
    assert "File too large" in one_error_line(proc)
    assert_last_good_state(prepared, manifest)


@contextlib.contextmanager
def read_only(path: Path):
    """A read-only view of `path`: a read-only bind mount as root (root ignores modes), else chmod."""
    if os.geteuid() == 0:
        ro = path.with_name(path.name + "_ro")
        ro.mkdir()
        ok = subprocess.run(["mount", "--bind", "-o", "ro", str(path), str(ro)], capture_output=True).returncode == 0
        if ok:
            try:
                yield ro
            finally:
                subprocess.run(["umount", "-l", str(ro)], capture_output=True)
            return
    modes = {p: p.stat().st_mode for p in [path, *path.rglob("*")] if p.is_dir()}
    for p in modes:
        p.chmod(0o555)
    try:
        yield path
    finally:
        for p, m in modes.items():
            p.chmod(m)


def test_read_only_workspace(prepared, tmp_path):
    manifest = (prepared / "scene" / "manifest.json").read_text()
    with read_only(prepared) as ws:
        probe = ws / "probe"
        try:
            probe.write_text("x")
            pytest.fail("the workspace is still writable")
        except OSError:
            pass
        proc = run_cli(["-q", "--config", tmp_path / "wgs.toml", "-w", ws, "coarse"], tmp_path)
        assert proc.returncode == 2, proc.stderr
        line = one_error_line(proc)
        assert str(ws) in line and "not writable" in line
        info = run_cli(["-w", ws, "info"], tmp_path)  # reading still works
        assert info.returncode == 0 and "4 training views" in info.stdout, info.stderr
    assert_last_good_state(prepared, manifest)


def test_second_writer_is_refused_naming_the_holder(prepared, tmp_path):
    cfg = tmp_path / "wgs.toml"
    cfg.write_text(FAST.replace("iterations = 60", "iterations = 3000"))
    first = subprocess.Popen(
        [sys.executable, "-m", "wgs", "-q", "--config", str(cfg), "-w", str(prepared), "coarse"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        t0 = time.monotonic()
        while not (prepared / ".wgs.lock").exists():
            assert first.poll() is None and time.monotonic() - t0 < 60
            time.sleep(0.05)
        proc = run_cli(["-q", "-w", prepared, "coarse"], tmp_path)
        assert proc.returncode == 2
        line = one_error_line(proc)
        assert f"in use by pid {first.pid} on {os.uname().nodename} since 20" in line
    finally:
        first.kill()
        first.wait()
