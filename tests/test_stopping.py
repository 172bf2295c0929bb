"""The held-out stopping rule: where a curve stops gaining (`gaussians.stopping`), and the coarse
stage stopping there, saying why, and keeping that stop across a resume."""

import json
import signal
import subprocess

import pytest
import torch
from conftest import TINY_HELD_OUT, make_scene
from test_resume import start_and_signal_when, wgs_cmd

from wgs.gaussians.stopping import mean_curve, pilot_cap, plateau_iteration, smoothed, still_gaining


def rising_then_falling(peak=300, top=20.0, end=600, every=25):
    return [(it, top - abs(it - peak) / 100) for it in range(0, end + 1, every)]


def test_plateau_is_the_first_iteration_within_the_tolerance_of_the_best():
    curve = rising_then_falling()
    assert plateau_iteration(curve, 0.0) == 300
    assert plateau_iteration(curve, 0.1) == 300  # 275's 19.75 is 0.25 below
    assert plateau_iteration(curve, 0.3) == 275
    assert plateau_iteration([(0, 5.0), (10, 5.0)], 0.0) == 0


def test_still_gaining_until_patience_passes_without_a_better_score():
    curve = rising_then_falling(peak=300, end=500)
    assert still_gaining(curve[:5], 0.1, 250)  # shorter than the patience
    assert still_gaining(curve[: 13 + 1], 0.1, 250)  # the best (at 300) came within the last 250
    assert not still_gaining(curve, 0.1, 150)  # 350..500 brought nothing better than 300's
    flat = [(it, 10.0 + 0.01 * (it // 25)) for it in range(0, 501, 25)]  # 0.01 dB a probe
    assert not still_gaining(flat, 0.1, 100)  # gains below the tolerance do not count
    assert still_gaining(flat, 0.1, 300)


def test_mean_curve_holds_an_ended_pilot_at_its_last_score_and_smoothing_averages_a_window():
    a = [(0, 10.0), (25, 12.0), (50, 14.0)]
    b = [(0, 12.0), (25, 14.0)]  # ended at 25
    assert mean_curve([a, b]) == [(0, 11.0), (25, 13.0), (50, 14.0)]
    assert smoothed(a, 50) == [(0, 10.0), (25, 11.0), (50, 13.0)]
    assert smoothed(a, 1) == a


def test_a_pilot_runs_no_further_than_its_curve_can_shorten_the_run():
    cap = pilot_cap(1500, 3.0, 250)
    assert cap == 750
    assert round(3.0 * (cap - 250)) >= 1500  # a plateau seen only at the cap leaves all 1500 iterations
    assert pilot_cap(300, 1.0, 250) == 300  # never past the run itself
    assert pilot_cap(1000, 3.0, 250) == 584


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    base = tmp_path_factory.mktemp("stopping")
    return make_scene(base / "scene", seed=2, size=64, n_train=4, n_test=5), base


def coarse_cfg(base, name: str, extra: str):
    cfg = TINY_HELD_OUT.replace(
        "[coarse]\niterations = 30\nrefine_start = 10\nrefine_every = 10",
        "[coarse]\niterations = 120\nrefine_start = 20\nrefine_every = 20\nstop_every = 10\nstop_patience = 40\n"
        + extra,
    ).replace("ensemble = 2", "ensemble = 1")
    assert cfg != TINY_HELD_OUT
    path = base / name
    path.write_text(cfg)
    return path


def prepared_and_coarse(ws, cfg, scene) -> tuple[str, dict, list[str]]:
    """`wgs prepare` and `wgs coarse`: what coarse said (one line), its manifest, the photos' names."""
    subprocess.run(wgs_cmd(ws, cfg, "prepare", str(scene)), check=True, capture_output=True)
    proc = subprocess.run(wgs_cmd(ws, cfg, "coarse", quiet=False), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    photos = json.loads((ws / "scene/scene.json").read_text())["train_names"]
    return " ".join(proc.stderr.split()), json.loads((ws / "1_coarse/manifest.json").read_text()), photos


def test_coarse_stops_where_the_pilots_stopped_gaining_says_why_and_resumes_to_the_same_model(tiny, tmp_path):
    scene, base = tiny
    # a tolerance no score misses: the pilots' plateau is iteration 0, so the models stop at stop_min_iterations
    cfg = coarse_cfg(base, "stop.toml", "stop_tolerance_db = 100.0\nstop_min_iterations = 50\n")
    ref = tmp_path / "ref"
    said, m, photos = prepared_and_coarse(ref, cfg, scene)
    assert "coarse: stops at iteration 50 of 120, 3 x 0, where the held-out PSNR of 4 pilots" in said, said
    assert m["iterations"] == 50 and m["stopping"]["stop_at"] == 50
    assert list(m["stopping"]["pilot_iterations"]) == photos
    assert all(40 <= n <= 120 for n in m["stopping"]["pilot_iterations"].values())  # each ran out its patience

    # killed in G_c's loop, after the pilots saved where to stop: the resumed run stops there too
    ws = tmp_path / "ws"
    subprocess.run(wgs_cmd(ws, cfg, "prepare", str(scene)), check=True, capture_output=True)
    killed = start_and_signal_when(wgs_cmd(ws, cfg, "coarse"), ws / ".resume/1_coarse/gc.pt", signal.SIGKILL)
    killed.communicate(timeout=120)
    assert (ws / ".resume/1_coarse/stop.pt").is_file()
    res = subprocess.run(wgs_cmd(ws, cfg, "coarse", resume=True, quiet=False), capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "the pilots ran before the interruption: their stop is kept" in " ".join(res.stderr.split())
    assert "stops at iteration 50 of 120" in " ".join(res.stderr.split())
    a = torch.load(ws / "1_coarse/ckpt.pt", weights_only=True)["splats"]
    b = torch.load(ref / "1_coarse/ckpt.pt", weights_only=True)["splats"]
    assert all(torch.equal(a[k], b[k]) for k in b)


def test_stop_iterations_trains_every_iteration_and_runs_no_pilot(tiny, tmp_path):
    scene, base = tiny
    said, m, _ = prepared_and_coarse(tmp_path / "ws", coarse_cfg(base, "all.toml", 'stop = "iterations"\n'), scene)
    assert "stops at iteration" not in said
    assert m["iterations"] == 120 and m["stopping"] is None


def test_the_report_says_where_the_coarse_stage_stopped(finished_workspace):
    base, _ = finished_workspace
    m = json.loads((base / "ws/1_coarse/manifest.json").read_text())
    report = " ".join((base / "ws/6_eval/report.md").read_text().split())
    assert f"coarse stopped at iteration {m['stopping']['stop_at']}: the held-out PSNR of 4 pilots" in report


def test_at_most_stop_pilots_pilots_spread_over_the_photos(tiny, tmp_path):
    scene, base = tiny
    _, m, photos = prepared_and_coarse(tmp_path / "ws", coarse_cfg(base, "two.toml", "stop_pilots = 2\n"), scene)
    assert list(m["stopping"]["pilot_iterations"]) == [photos[0], photos[2]]
    assert all(n <= pilot_cap(120, 3.0, 40) == 80 for n in m["stopping"]["pilot_iterations"].values())
