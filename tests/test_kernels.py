"""The numba kernels compiled at once (`wgs.kernels`): a first run says why it waits, and a whole
run afterwards compiles nothing more."""

import json
import os
import subprocess
import sys

import pytest
from conftest import TINY, make_scene

from wgs import kernels, progress
from wgs.context import RunOptions

# in a fresh process: compile (or load) the kernels, run `wgs all` on a tiny scene with the mirror
# check (the hull's votes, silhouettes and the mirror's IoUs) in that process, then the signatures
# each kernel holds before and after
WHOLE_RUN = """
import json, sys
from click.testing import CliRunner
from wgs import kernels
from wgs.cli import cli
kernels.compile_kernels()
before = {k.__name__: sorted(map(str, k.signatures)) for k in kernels.kernels()}
res = CliRunner().invoke(cli, ["-q", "--config", sys.argv[1], "-w", sys.argv[2], "all", sys.argv[3]])
assert res.exit_code == 0, (res.output, repr(res.exception))
after = {k.__name__: sorted(map(str, k.signatures)) for k in kernels.kernels()}
print(json.dumps({"before": before, "after": after}))
"""


@pytest.mark.slow
def test_a_whole_run_compiles_no_kernel_beyond_compile_kernels(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=3, size=48, n_train=4, n_test=2)
    cfg = tmp_path / "wgs.toml"
    cfg.write_text(TINY.replace('mirror = "none"', 'mirror = "outline"'))
    assert cfg.read_text() != TINY
    proc = subprocess.run(
        [sys.executable, "-c", WHOLE_RUN, str(cfg), str(tmp_path / "ws"), str(scene)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    sigs = json.loads(proc.stdout.splitlines()[-1])
    assert set(sigs["before"]) == {k.__name__ for k in kernels.kernels()}
    # the entry points compiled (`_touches` runs only inside other kernels)
    entry_points = ("_forward", "_backward", "hull_votes", "first_hit", "mirror_ious", "kept_under_rotations")
    assert all(sigs["before"][name] for name in entry_points)
    assert sigs["after"] == sigs["before"]


def test_an_empty_cache_is_not_cached(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    code = "from wgs import kernels; print(kernels.cached(), kernels.cache_dir())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", str(tmp_path / "numba")]


def test_a_cold_cache_is_compiled_with_one_line_before_and_after(monkeypatch, capsys):
    ran = []
    monkeypatch.setattr(kernels, "cached", lambda: False)
    monkeypatch.setattr(kernels, "compile_kernels", lambda: ran.append(1) or 24.6)
    monkeypatch.setattr(progress, "_quiet", False)
    monkeypatch.setattr(progress.console, "quiet", False)
    RunOptions(None, "cpu", 0, False).torch_device()
    said = " ".join(capsys.readouterr().err.split())
    assert ran == [1]
    assert "numba: compiling the CPU kernels, once (about half a minute on 2 cores; cached in" in said, said
    assert "numba: compiled in 25 s" in said, said


def test_a_warm_cache_says_nothing(monkeypatch, capsys):
    monkeypatch.setattr(kernels, "cached", lambda: True)
    monkeypatch.setattr(kernels, "compile_kernels", lambda: pytest.fail("compiled a cached kernel"))
    monkeypatch.setattr(progress, "_quiet", False)
    monkeypatch.setattr(progress.console, "quiet", False)
    RunOptions(None, "cpu", 0, False).torch_device()
    assert "numba" not in capsys.readouterr().err.replace("rasterizer: numba", "")
