"""The held-out stopping rule: where a curve stops gaining (`gaussians.stopping`), and the coarse and fine
stage stopping there, saying why, and keeping that stop across a resume."""

import dataclasses
import json
import signal

import pytest
import torch
from conftest import TINY_HELD_OUT, make_scene, run_wgs
from test_resume import assert_same_model, copy_workspace, start_and_signal_when, wgs_args, wgs_cmd

from wgs.gaussians.stopping import mean_curve, pilot_cap, plateau_iteration, plateau_past, smoothed, still_gaining


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


def test_a_pilot_ends_once_its_plateau_lies_past_where_the_run_keeps_every_iteration():
    rising = [(it, 10.0 + it / 100) for it in range(0, 751, 25)]  # +0.25 dB every 25 iterations
    assert plateau_past(rising[: 21 + 1], 500, 0.1)  # 525 beats everything up to 500 by 0.25
    assert not plateau_past(rising[: 20 + 1], 500, 0.1)  # nothing past 500 yet
    slow = [(it, 10.0 + it / 1000) for it in range(0, 751, 25)]
    assert not plateau_past(slow[: 22 + 1], 500, 0.1)  # 550: +0.05 dB, within the tolerance
    assert plateau_past(slow, 500, 0.1)
    # each pilot cut where it shows so: the mean curve's plateau still lies past the point
    ends = [next(k for k in range(len(c)) if plateau_past(c[: k + 1], 500, 0.1)) for c in (rising, slow)]
    cut = [c[: k + 1] for c, k in zip((rising, slow), ends, strict=True)]
    assert plateau_iteration(mean_curve(cut), 0.1) > 500
    assert not plateau_past([(0, 10.0), (500, 14.0), (525, 13.0), (550, 14.05)], 500, 0.1)  # peaked by 500


def test_a_member_carries_on_from_its_pilot_only_where_the_models_stop_early(tmp_path):
    """Member k + 1 carries on from pilot k's kept state where the models stop before their last
    iteration (or always, as asked) and the pilot ended before that stop; G_c, a member without a
    pilot, a pilot that ran to the stop or kept nothing, and a stop at the last iteration: from the start."""
    from wgs.stages.coarse.run import member_start, pilot_state
    from wgs.stages.coarse.settings import CoarseConfig
    from wgs.workspace import StageRun

    run, cfg = StageRun("coarse", tmp_path / "out"), CoarseConfig(iterations=1500, ensemble=6)
    stop = {"stop_at": 1200, "pilot_iterations": {"a.png": 675, "b.png": 1200, "c.png": 600}}
    for k in (0, 1):
        pilot_state(run, cfg, k).write_bytes(b"")
    assert [member_start(run, cfg, stop, i) for i in range(6)] == [
        None,
        pilot_state(run, cfg, 0),
        None,
        None,
        None,
        None,
    ]
    late = {**stop, "stop_at": 1500}  # the models train every iteration
    assert member_start(run, cfg, late, 1) is None
    assert member_start(run, dataclasses.replace(cfg, members_from_pilots="always"), late, 1) == pilot_state(
        run, cfg, 0
    )
    never = dataclasses.replace(cfg, members_from_pilots="never")
    assert pilot_state(run, never, 0) is None and member_start(run, never, stop, 1) is None
    assert pilot_state(run, dataclasses.replace(cfg, ensemble=1), 0) is None  # no member to carry on


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny scene and a workspace where `wgs prepare` ran on it once (every config below has
    TINY's prepare settings): each test starts from a copy at the coarse stage."""
    base = tmp_path_factory.mktemp("stopping")
    scene = make_scene(base / "scene", seed=2, size=64, n_train=4, n_test=5)
    assert (
        run_wgs(
            wgs_args(base / "prepared", coarse_cfg(base, "prepare.toml", ""), "prepare", str(scene)), base
        ).returncode
        == 0
    )
    return scene, base


def coarse_cfg(base, name: str, extra: str, ensemble: int = 1):
    cfg = TINY_HELD_OUT.replace(
        "[coarse]\niterations = 30\nrefine_start = 10\nrefine_every = 10",
        "[coarse]\niterations = 120\nrefine_start = 20\nrefine_every = 20\nstop_every = 10\nstop_patience = 40\n"
        + extra,
    ).replace("ensemble = 2", f"ensemble = {ensemble}")
    assert cfg != TINY_HELD_OUT
    path = base / name
    path.write_text(cfg)
    return path


def prepared_and_coarse(ws, cfg, scene) -> tuple[str, dict, list[str]]:
    """`wgs coarse` after the shared prepare: what coarse said (one line), its manifest, the photos' names."""
    copy_workspace(scene.parent / "prepared", ws)
    proc = run_wgs(wgs_args(ws, cfg, "coarse", quiet=False), ws)
    assert proc.returncode == 0, proc.stderr
    photos = json.loads((ws / "scene/scene.json").read_text())["train_names"]
    return " ".join(proc.stderr.split()), json.loads((ws / "1_coarse/manifest.json").read_text()), photos


@pytest.mark.slow
def test_coarse_and_fine_stop_where_the_pilots_stopped_gaining_say_why_and_resume_to_the_same_models(tiny, tmp_path):
    """A tolerance no score misses: the pilots' plateau is iteration 0, so the coarse models stop at
    stop_min_iterations (50 of 120), and G_f, which follows them (the coarse stage's margin times
    their plateau, of its own iterations), at 50 of its 120. Each pilot ends at 40, its patience;
    the ensemble's second model carries on from the first pilot's state, given the photo that pilot
    held out, for its last 10 iterations. Each stage killed in its loop (the coarse stage in that
    member's) resumes to the uninterrupted run's models; `--stop iterations` trains all of G_f's
    iterations. Once the pilots ended the estimate of the rest takes their plateau in place of the
    expected one: the coarse models (without the pilots) and G_f are modelled at 50 iterations,
    G_d (all its iterations) as before."""
    scene, base = tiny
    cfg = coarse_cfg(base, "stop.toml", "stop_tolerance_db = 100.0\nstop_min_iterations = 50\n", ensemble=2)
    cfg.write_text(
        cfg.read_text().replace(
            "[fine]\niterations = 20\nrefine_start = 5\nrefine_every = 5",
            "[fine]\niterations = 120\nrefine_start = 20\nrefine_every = 20",
        )
    )
    assert "[fine]\niterations = 120" in cfg.read_text()
    ref = copy_workspace(base / "prepared", tmp_path / "ref")
    proc = run_wgs(wgs_args(ref, cfg, "all", str(scene), quiet=False), tmp_path)
    assert proc.returncode == 0, proc.stderr
    said = " ".join(proc.stderr.split())
    assert "coarse: stops at iteration 50 of 120, 3 x 0, where the held-out PSNR of 4 pilots" in said, said
    m = json.loads((ref / "1_coarse/manifest.json").read_text())
    assert m["iterations"] == 50 and m["stopping"]["stop_at"] == 50
    assert list(m["stopping"]["pilot_iterations"]) == json.loads((ref / "scene/scene.json").read_text())["train_names"]
    assert set(m["stopping"]["pilot_iterations"].values()) == {40}  # each ran out its patience
    assert "coarse: 1 ensemble member(s) carry on from the pilots" in said, said
    photos = list(m["stopping"]["pilot_iterations"])
    assert m["carried_members"] == {"2": photos[0]}
    member = torch.load(ref / "1_coarse/members/ckpt_1.pt", weights_only=True)
    assert member["step"] == 50
    assert "fine: stops at iteration 50 of 120, 3 x 0, where the coarse stage's pilots" in said, said
    m = json.loads((ref / "5_fine/manifest.json").read_text())
    assert m["iterations"] == 50 and m["stopping"] == {
        "rule": "coarse pilots",
        "plateau": 0,
        "margin": 3.0,
        "stop_at": 50,
    }
    # the estimate of the rest once the pilots ended, before the coarse models train: the models
    # without the pilots, and they and G_f at 50 of their 120 iterations, not all
    line = "estimate of the rest, the coarse pilots' plateau at 0 (expected 625): about"
    assert line in said, said
    assert said.index("coarse: stops at iteration 50") < said.index(line) < said.index("model(s) from seeds"), said
    record = json.loads((ref / "run.json").read_text())
    before, after = record["estimate"], record["estimate_after_pilots"]
    assert list(after) == list(before)
    assert after["coarse"] < before["coarse"] and after["fine"] < before["fine"]
    assert all(after[t] == before[t] for t in ("mask_data", "finetune", "repair", "eval"))
    coarse = json.loads((ref / "1_coarse/manifest.json").read_text())
    assert 0 < coarse["stopping"]["pilots_s"] < coarse["wall_time_s"]
    report = " ".join((ref / "6_eval/report.md").read_text().split())
    assert "coarse, mask_data, finetune, repair, fine were estimated at" in report, report
    assert "fine stopped at iteration 50: 3 times the plateau of the coarse stage's pilots (iteration 0)" in report

    # killed in the member's loop, after the pilots saved where to stop and their states: the
    # resumed run stops there too, with the same models
    ws = copy_workspace(base / "prepared", tmp_path / "ws")
    killed = start_and_signal_when(wgs_cmd(ws, cfg, "coarse"), ws / ".resume/1_coarse/gc1.pt", signal.SIGKILL)
    killed.communicate(timeout=120)
    assert (ws / ".resume/1_coarse/stop.pt").is_file()
    res = run_wgs(wgs_args(ws, cfg, "coarse", resume=True, quiet=False), tmp_path)
    assert res.returncode == 0, res.stderr
    assert "the pilots ran before the interruption: their stop is kept" in " ".join(res.stderr.split())
    assert "stops at iteration 50 of 120" in " ".join(res.stderr.split())
    assert_same_model(ws, ref, "1_coarse")
    again = torch.load(ws / "1_coarse/members/ckpt_1.pt", weights_only=True)
    assert all(torch.equal(again["splats"][k], member["splats"][k]) for k in member["splats"])

    # killed in G_f's loop: the resumed stage stops at the same iteration with the same model
    ws = copy_workspace(ref, tmp_path / "ws_fine", ("scene", "1_coarse", "2_mask_data", "3_finetune", "4_repair"))
    killed = start_and_signal_when(wgs_cmd(ws, cfg, "fine"), ws / ".resume/5_fine/gf.pt", signal.SIGKILL)
    killed.communicate(timeout=120)
    assert 0 < torch.load(ws / ".resume/5_fine/gf.pt", weights_only=True)["it"] < 50
    res = run_wgs(wgs_args(ws, cfg, "fine", resume=True, quiet=False), tmp_path)
    assert res.returncode == 0, res.stderr
    assert "stops at iteration 50 of 120" in " ".join(res.stderr.split())
    assert_same_model(ws, ref, "5_fine")

    res = run_wgs(wgs_args(ws, cfg, "fine", "--stop", "iterations", "--iterations", "60"), tmp_path)
    assert res.returncode == 0, res.stderr
    m = json.loads((ws / "5_fine/manifest.json").read_text())
    assert m["iterations"] == 60 and m["stopping"] is None


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
