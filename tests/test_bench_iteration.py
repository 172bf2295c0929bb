"""`python -m tools.bench iteration --stage fine`: the fine stage's own iteration, profiled by phase."""

import shutil

import pytest

from tools.bench import PHASES, bench_iteration
from wgs.config import resolve


def test_the_fine_iteration_is_profiled_with_its_pseudo_view(finished_workspace, tmp_path):
    base, _ = finished_workspace
    ws = tmp_path / "ws"
    shutil.copytree(base / "ws", ws)
    res = bench_iteration("", str(tmp_path), 4, 1, window=4, stage="fine", workspace=str(ws), start=5)
    phases = res["phases_ms"]
    assert set(PHASES) <= set(phases)
    assert phases["wgs:pseudo_view"] > 0 and phases["wgs:render"] > 0 and phases["wgs:backward"] > 0
    # the phases and the rest add up to the measured iteration
    assert sum(phases.values()) == pytest.approx(res["ms_per_iteration_profiled"], abs=0.01)
    assert res["stage"] == "fine" and res["iterations"] == f"6..9 of {resolve('fine').iterations}"
    assert res["half_size_through"] == 9  # G_f's early iterations train at half size, as the coarse ones do


def test_a_window_in_the_half_size_phase_keeps_the_phase(blender_scene, tmp_path):
    """The bench trains only up to its window's end; the half-size phase still ends where the stage's
    own schedule ends it, so a window inside it is profiled at half size."""
    cfg = resolve("coarse")
    res = bench_iteration(str(blender_scene), str(tmp_path), 4, 1, window=3, start=4)
    assert res["iterations"] == f"5..7 of {cfg.iterations}"
    assert int(cfg.half_size_until * cfg.iterations) > 7 and res["half_size_through"] == 7  # the whole window
