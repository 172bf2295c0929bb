"""The run-time estimate, the working size chosen for the machine, and the time budget (wgs.estimate)."""

import dataclasses
import json

import pytest
import torch
from conftest import expect_error, run_wgs

from wgs.config import STAGES, load_config_file, resolve
from wgs.cost import (
    EXPECTED_PLATEAU,
    FIT_MASK_SHARE,
    GPU_MAX_SIZE,
    HULL_PLATEAU_LINE,
    MASK_SHARE_SLOPE,
    MIN_SHARE_FACTOR,
    NO_MASKS_FACTOR,
    Calibration,
    SceneFacts,
    cover_factor,
    expected_follow_end,
    expected_iterations,
    loop_s,
    plateau_from_hull,
    time_boxed,
)
from wgs.errors import InputError
from wgs.estimate import (
    CALIBRATION_HISTORY,
    CALIBRATION_HISTORY_S,
    CALIBRATION_MAX_AGE_S,
    MIN_SIZE,
    RunTiming,
    budget_plan,
    cached_calibration,
    calibrate,
    choose_downscale,
    costs,
    hull_loo_iou,
    machine_key,
    parse_duration,
    probe_s,
    stage_seconds,
)
from wgs.scene.prepare import downscale_for
from wgs.stages.coarse.settings import (
    MODELS_FACTOR,
    model_config,
    model_start,
    pilot_iterations,
    pilots_s,
    with_found_stop,
)

# about this 2-core CPU's figures (a calibration made here)
CAL = Calibration(
    raster=(0.008, 5.5e-7), d_step_s=0.12, d_forward_s_per_pixel=2.3e-6, threads=2, device="cpu", seconds=3.0
)


def configs(preset=None, **tables):
    cfgs = {t: resolve(t, preset) for t in STAGES}
    for t, fields in tables.items():
        cfgs[t] = dataclasses.replace(cfgs[t], **fields)
    return cfgs


def test_smoke_calibrate_cpu():
    cal = calibrate(torch.device("cpu"))
    assert cal.device == "cpu" and cal.threads >= 1
    assert cal.d_step_s > 0 and cal.d_forward_s_per_pixel > 0
    assert cal.view_s(256 * 256) > cal.view_s(64 * 64) > 0


def test_calibration_cached_for_an_hour(tmp_path, monkeypatch):
    monkeypatch.setenv("WGS_CACHE", str(tmp_path))
    calls = []
    monkeypatch.setattr("wgs.estimate.calibrate", lambda device: calls.append(device) or CAL)
    monkeypatch.setattr("wgs.estimate.probe_s", lambda device: 0.010)
    assert cached_calibration(torch.device("cpu"), now=1000.0) == CAL
    assert cached_calibration(torch.device("cpu"), now=1000.0 + CALIBRATION_MAX_AGE_S / 2) == CAL
    assert len(calls) == 1
    cached_calibration(torch.device("cpu"), now=1000.0 + 2 * CALIBRATION_MAX_AGE_S)
    assert len(calls) == 2
    (tmp_path / "calibration.json").write_text("{broken")
    assert cached_calibration(torch.device("cpu"), now=1.0) == CAL  # a broken cache is made again


def test_calibration_made_on_a_busier_machine_is_made_again(tmp_path, monkeypatch):
    """A cached calibration whose probe ran slower than the probe now (another run's processes were
    busy then) is timed again; one made on a machine as idle as now, or idler, is kept."""
    monkeypatch.setenv("WGS_CACHE", str(tmp_path))
    calls, probes = [], iter([0.016, 0.016, 0.013, 0.010, 0.010, 0.016])
    monkeypatch.setattr("wgs.estimate.calibrate", lambda device: calls.append(device) or CAL)
    monkeypatch.setattr("wgs.estimate.probe_s", lambda device: next(probes))
    cpu = torch.device("cpu")
    cached_calibration(cpu, now=1000.0)  # made busy: 16 ms (before and after calibrating)
    cached_calibration(cpu, now=1001.0)  # 13 ms now: within BUSIER_RATIO, kept
    assert len(calls) == 1
    cached_calibration(cpu, now=1002.0)  # 10 ms now: made again, and its probe recorded
    assert len(calls) == 2
    assert [e["probe_s"] for e in json.loads((tmp_path / "calibration.json").read_text()).popitem()[1]] == [0.010]
    cached_calibration(cpu, now=1003.0)  # busier now (16 ms): the idle calibration is kept
    assert len(calls) == 2


def test_the_median_of_the_days_calibrations_times_the_machine(tmp_path, monkeypatch):
    """One calibration an hour: the estimate uses the median of those of the last day (the newest
    CALIBRATION_HISTORY), so that one made at a quick moment moves it less; a cache of one record,
    as older versions wrote it, counts as the first."""
    monkeypatch.setenv("WGS_CACHE", str(tmp_path))
    steps = iter([0.100, 0.080, 0.140, 0.110, 0.090, 0.130, 0.120, 0.150])
    monkeypatch.setattr("wgs.estimate.calibrate", lambda device: dataclasses.replace(CAL, d_step_s=next(steps)))
    monkeypatch.setattr("wgs.estimate.probe_s", lambda device: 0.010)
    old = {"made": 0.0, "probe_s": 0.010, "calibration": dataclasses.asdict(dataclasses.replace(CAL, d_step_s=0.5))}
    (tmp_path / "calibration.json").write_text(json.dumps({machine_key(torch.device("cpu")): old}))
    cpu, hour = torch.device("cpu"), CALIBRATION_MAX_AGE_S + 1.0
    got = [cached_calibration(cpu, now=i * hour).d_step_s for i in range(1, 8)]
    assert got[0] == pytest.approx((0.5 + 0.100) / 2)  # the old record and the first new one
    assert got[1] == pytest.approx(0.100)  # 0.5, 0.100, 0.080
    assert got[2] == pytest.approx((0.100 + 0.140) / 2)  # 0.5, 0.100, 0.080, 0.140
    # five at most: 0.100, 0.080, 0.140, 0.110, 0.090 -> 0.100; then 0.080 ... 0.130 -> 0.110
    assert got[4:6] == pytest.approx([0.100, 0.110])
    assert len(json.loads((tmp_path / "calibration.json").read_text()).popitem()[1]) == CALIBRATION_HISTORY
    # within the hour the held ones are reused; a day later they are forgotten
    assert cached_calibration(cpu, now=7 * hour + 1.0).d_step_s == got[6]
    assert cached_calibration(cpu, now=8 * hour + CALIBRATION_HISTORY_S).d_step_s == pytest.approx(0.150)


def test_smoke_probe_s_cpu():
    assert 0 < probe_s(torch.device("cpu")) < 5.0


def test_stage_seconds_grow_with_size_and_iterations():
    small = stage_seconds(CAL, configs(), SceneFacts(128, 128, 4, 8))
    large = stage_seconds(CAL, configs(), SceneFacts(256, 256, 4, 8))
    every = stage_seconds(CAL, configs(coarse={"stop": "iterations"}), SceneFacts(128, 128, 4, 8))
    longer = stage_seconds(CAL, configs(coarse={"iterations": 3000, "stop": "iterations"}), SceneFacts(128, 128, 4, 8))
    assert set(small) == set(STAGES)
    for t in ("coarse", "mask_data", "fine", "repair", "eval"):
        assert large[t] > small[t]
    assert longer["coarse"] > 1.8 * (every["coarse"] - 25 * CAL.d_step_s)
    assert longer["fine"] == every["fine"]  # the coarse stage's iterations are not G_f's
    assert small["fine"] == every["fine"]  # the expected plateau's stop (3 x 625) is past the 1500 iterations
    early = stage_seconds(CAL, configs(coarse={"stop_margin": 1.5}), SceneFacts(128, 128, 4, 8))
    assert early["fine"] < every["fine"]  # under the held-out rule G_f stops where the coarse models do
    fast = stage_seconds(CAL, configs("fast"), SceneFacts(128, 128, 4, 8))
    assert sum(fast.values()) < sum(small.values()) / 3
    # the ensemble's other models longer at half size: a shorter stage, but not below G_c's share of it
    halved = stage_seconds(CAL, configs(coarse={"member_half_size_until": 1.0}), SceneFacts(128, 128, 4, 8))
    assert small["coarse"] / 2 < halved["coarse"] < small["coarse"]


def test_the_held_out_rule_is_modelled_as_its_margin_times_the_expected_plateau_plus_its_pilots():
    cfg = configs()["coarse"]
    assert cfg.stop == "held-out"
    assert expected_iterations(cfg) == min(cfg.iterations, round(cfg.stop_margin * EXPECTED_PLATEAU))
    assert expected_iterations(dataclasses.replace(cfg, stop="iterations")) == cfg.iterations
    assert expected_iterations(dataclasses.replace(cfg, max_seconds=60.0)) == cfg.iterations  # the budget decides
    facts = SceneFacts(128, 128, 4, 8)
    assert pilots_s(CAL, cfg, facts, 1) > 0 == pilots_s(CAL, dataclasses.replace(cfg, stop="iterations"), facts, 1)
    # twice the iterations with a margin of 1.5: the stop (1.5 x 625) is below both, and more of it in
    # the schedule's half-size share
    early = {"stop_margin": 1.5}
    longer = stage_seconds(CAL, configs(coarse={**early, "iterations": 3000}), facts)
    assert 0.5 < longer["coarse"] / stage_seconds(CAL, configs(coarse=early), facts)["coarse"] < 1
    # G_f stops at the coarse stage's margin times the expected plateau, of its own iterations
    fine = configs()["fine"]
    assert expected_follow_end(fine, cfg) == min(fine.iterations, round(cfg.stop_margin * EXPECTED_PLATEAU))
    assert expected_follow_end(dataclasses.replace(fine, stop="iterations"), cfg) is None
    assert expected_follow_end(dataclasses.replace(fine, max_seconds=60.0), cfg) is None  # the budget decides
    assert expected_follow_end(fine, dataclasses.replace(cfg, stop="iterations")) is None
    # once the pilots ran, their plateau (100: a stop at 300) in place of the expected one
    found = dataclasses.replace(facts, plateau=100)
    assert expected_follow_end(configs()["fine"], cfg, found.plateau) == 300
    after, usual = stage_seconds(CAL, configs(), found), stage_seconds(CAL, configs(), facts)
    assert after["fine"] < 0.5 * usual["fine"]
    assert all(after[t] == usual[t] for t in ("mask_data", "finetune", "repair", "eval"))
    # and the coarse stage is its models alone (the pilots have run), stopped at 300
    assert with_found_stop(cfg, found).end_iteration == 300 and with_found_stop(cfg, facts) is cfg
    assert after["coarse"] < 0.5 * usual["coarse"]
    late = dataclasses.replace(facts, plateau=1000)  # a stop past the last iteration: all of them, no pilots
    (before, _), (models, _) = costs(CAL, configs(), facts)["coarse"], costs(CAL, configs(), late)["coarse"]
    assert before.other_s > 0 == models.other_s and models.loop_s == before.loop_s
    assert models.factor == pytest.approx(MODELS_FACTOR * before.factor)  # what lego's models took over their model


def test_members_that_carry_on_from_the_pilots_are_modelled_from_where_the_pilots_end():
    """A margin of 1.5 puts the expected stop (938) before the last iteration: the members carry on
    from the pilots. The usual capture's expected stop trains all the iterations: none does."""
    early = {"stop_margin": 1.5}
    cfg, facts = configs(coarse=early)["coarse"], SceneFacts(128, 128, 4, 8)
    n = pilot_iterations(cfg)
    assert 0 < n < expected_iterations(cfg) < cfg.iterations
    # G_c trains from the start; a member per pilot (4) from where it ended; the sixth model from the start
    assert [model_start(cfg, facts, i) for i in range(cfg.ensemble)] == [0, n, n, n, n, 0]
    assert model_start(cfg, SceneFacts(128, 128, 3, 8), 4) == 0  # 3 photos: 3 pilots
    assert model_start(dataclasses.replace(cfg, members_from_pilots="never"), facts, 1) == 0
    assert model_start(dataclasses.replace(cfg, stop="iterations"), facts, 1) == 0  # no pilots
    usual = configs()["coarse"]
    assert [model_start(usual, facts, i) for i in range(usual.ensemble)] == [0] * usual.ensemble
    assert model_start(dataclasses.replace(usual, members_from_pilots="always"), facts, 1) == pilot_iterations(usual)
    # once the pilots ran (a plateau of 100: the models stop at 150), from where each ended; a
    # pilot that ended past the stop leaves its member to train from the start
    ran = dataclasses.replace(facts, plateau=100, pilot_ends=(90, 200, 120, 60))
    stopped = with_found_stop(cfg, ran)
    assert [model_start(stopped, ran, i) for i in range(cfg.ensemble)] == [0, 90, 0, 120, 60, 0]
    member = model_config(cfg, 1)
    assert loop_s(CAL, member, facts.pixels, start=n) < loop_s(CAL, member, facts.pixels)
    assert loop_s(CAL, member, facts.pixels, start=10**6) == 0.0
    apart = stage_seconds(CAL, configs(coarse={**early, "members_from_pilots": "never"}), facts)
    assert stage_seconds(CAL, configs(coarse=early), facts)["coarse"] < apart["coarse"]


def test_the_training_stages_grow_with_the_share_of_the_frame_the_object_covers():
    """The share lego's 4 views have (where the stages' factors were fitted) leaves the model as it was; a
    close-up's share lengthens the training loops only; no masks is its own factor; a tiny object
    is not modelled below MIN_SHARE_FACTOR."""
    cfgs = configs()
    at_fit = stage_seconds(CAL, cfgs, SceneFacts(128, 128, 4, 8))
    assert stage_seconds(CAL, cfgs, SceneFacts(128, 128, 4, 8, mask_share=FIT_MASK_SHARE)) == at_fit
    close = stage_seconds(CAL, cfgs, SceneFacts(128, 128, 4, 8, mask_share=0.8))
    fixed = {
        t: cost.fixed_steps * CAL.d_step_s for t, (cost, _) in costs(CAL, cfgs, SceneFacts(128, 128, 4, 8)).items()
    }
    for t in ("coarse", "mask_data", "fine"):
        work = at_fit[t] - fixed[t]
        grown = close[t] - fixed[t]
        assert grown / work == pytest.approx(1 + MASK_SHARE_SLOPE * (0.8 - FIT_MASK_SHARE), rel=0.01), t
    for t in ("finetune", "repair", "eval"):
        assert close[t] == at_fit[t]
    assert cover_factor(SceneFacts(128, 128, 4, 8, has_masks=False, mask_share=0.8)) == NO_MASKS_FACTOR
    assert cover_factor(SceneFacts(128, 128, 4, 8, mask_share=0.0)) == max(
        MIN_SHARE_FACTOR, 1 - MASK_SHARE_SLOPE * FIT_MASK_SHARE
    )


def test_plateau_expected_from_the_hulls_leave_one_out_iou():
    (low, early), (high, late) = HULL_PLATEAU_LINE
    assert plateau_from_hull(None) == EXPECTED_PLATEAU == late
    assert plateau_from_hull(low - 0.1) == plateau_from_hull(low) == early
    assert plateau_from_hull(high + 0.05) == late
    middle = [plateau_from_hull(low + k * (high - low) / 4) for k in range(5)]
    assert middle == sorted(middle) and early < middle[2] < late
    assert hull_loo_iou({"mirror": {"leave_one_out_iou": 0.6, "leave_one_out_iou_mirrored": 0.8}}) == 0.8
    assert hull_loo_iou({"mirror": None}) is None and hull_loo_iou({}) is None


def test_an_early_expected_plateau_shortens_the_coarse_and_fine_stages_only():
    usual = stage_seconds(CAL, configs(), SceneFacts(128, 128, 4, 8))
    early = stage_seconds(CAL, configs(), SceneFacts(128, 128, 4, 8, expected_plateau=125))
    assert early["coarse"] < 0.6 * usual["coarse"] and early["fine"] < 0.5 * usual["fine"]
    assert all(early[t] == usual[t] for t in ("mask_data", "finetune", "repair", "eval"))
    # the pilots are counted to the expected plateau and its patience; the members carry on from them
    cfg, facts = configs()["coarse"], SceneFacts(128, 128, 4, 8, expected_plateau=125)
    assert pilot_iterations(cfg, 125) == 125 + cfg.stop_patience
    assert model_start(cfg, facts, 1) == 125 + cfg.stop_patience
    # once the pilots ran, their plateau counts, not the expected one
    found = dataclasses.replace(facts, plateau=400, pilot_ends=(650,) * 4)
    assert stage_seconds(CAL, configs(), found) == stage_seconds(
        CAL, configs(), dataclasses.replace(found, expected_plateau=EXPECTED_PLATEAU)
    )


def test_prepare_records_the_mask_share_the_estimate_reads(finished_workspace):
    import numpy as np

    from wgs.io.images import find_with_stem, read_image, to_mask

    ws = finished_workspace[0] / "ws"
    info = json.loads((ws / "scene" / "scene.json").read_text())
    masks = [
        to_mask(read_image(find_with_stem(ws / "scene" / "masks", n.rsplit(".", 1)[0]))) for n in info["train_names"]
    ]
    share = info["masks"]["training_share"]
    assert 0.05 < share < 0.95 and share == pytest.approx(np.mean([(m > 0.5).mean() for m in masks]), abs=1e-4)
    scene = json.loads((ws / "run.json").read_text())["scene"]
    assert scene["mask_share"] == share
    assert scene["expected_plateau"] == plateau_from_hull(hull_loo_iou(info))  # from prepare's mirror check


def test_working_size_reads_the_given_masks_share(finished_workspace, tmp_path):
    """Before anything is loaded, the chooser's share of the given masks (here the images' alpha)
    is the one prepare records at the working size; photos without masks give none."""
    from wgs.io.images import read_image, split_rgba, write_png
    from wgs.scene.prepare import given_mask_share, load_scene_for_prepare

    base = finished_workspace[0]
    info = json.loads((base / "ws" / "scene" / "scene.json").read_text())
    scene = load_scene_for_prepare(base / "scene", None, 8)
    assert given_mask_share(scene, 10**8) == pytest.approx(info["masks"]["training_share"], abs=0.02)
    opaque = tmp_path / "opaque.png"
    write_png(opaque, split_rgba(read_image(scene.views[scene.train[0]].image))[0])
    scene.views[scene.train[0]].image = opaque
    assert given_mask_share(scene, 10**8) is None


def test_max_seconds_caps_a_stage():
    capped = stage_seconds(CAL, configs(fine={"max_seconds": 5.0}), SceneFacts(200, 200, 4, 8))
    assert capped["fine"] == pytest.approx(5.0 + 10 * CAL.d_step_s, abs=0.1)


def test_downscale_for():
    assert downscale_for(4000, 3000, 1600) == 3
    assert downscale_for(1600, 1200, 1600) == 1
    assert downscale_for(100, 80, 1600) == 1
    assert downscale_for(401, 300, 200) == 3


def test_choose_downscale_cpu_target_and_gpu():
    facts = SceneFacts(4000, 4000, 4, 8, full_pixels=16_000_000)
    k10, t10 = choose_downscale(CAL, configs(), facts, 600.0)
    k5, t5 = choose_downscale(CAL, configs(), facts, 300.0)
    assert k5 > k10 and t5 <= 300.0 and t10 <= 600.0
    # one size larger would not fit
    w, h = 4000 // (k10 - 1), 4000 // (k10 - 1)
    assert sum(stage_seconds(CAL, configs(), dataclasses.replace(facts, width=w, height=h)).values()) > 600.0
    # an impossible target: the smallest allowed size, and a time over the target
    k, t = choose_downscale(CAL, configs(), facts, 1.0)
    assert 4000 // (k + 1) < MIN_SIZE <= 4000 // k and t > 1.0
    # photos under twice that size keep their own, however slow the machine
    assert choose_downscale(CAL, configs(), SceneFacts(128, 96, 4, 8, full_pixels=128 * 96), 1.0)[0] == 1
    gpu = dataclasses.replace(CAL, device="cuda:0")
    assert choose_downscale(gpu, configs(), facts, None) == (downscale_for(4000, 4000, GPU_MAX_SIZE), None)


def test_budget_plan_fills_the_budget():
    facts = SceneFacts(200, 200, 4, 200)
    cfgs = configs()
    for left in (240.0, 600.0, 1200.0):
        plan = budget_plan(CAL, cfgs, facts, left)
        assert sum(plan["seconds"].values()) == pytest.approx(left, rel=0.02)
        for t in ("coarse", "mask_data", "fine"):
            boxed = plan["stages"][t]
            assert boxed.max_seconds > 0 and boxed.iterations >= cfgs[t].iterations
            assert boxed.refine_stop / boxed.iterations == pytest.approx(
                cfgs[t].refine_stop / cfgs[t].iterations, rel=0.01
            )
    # stages left out get no share
    plan = budget_plan(CAL, cfgs, facts, 300.0, runs=("coarse", "eval"))
    assert set(plan["seconds"]) == {"coarse", "eval"}


def test_time_boxed_scales_caps():
    cfg = resolve("coarse")
    boxed = time_boxed(cfg, 100.0, 50.0, 1.5)
    assert boxed.max_seconds == 100.0 and boxed.iterations == int(cfg.iterations * 3)
    assert time_boxed(cfg, 10.0, 50.0, 1.5).iterations == int(cfg.iterations * 1.5)


@pytest.mark.parametrize("text,seconds", [("10m", 600), ("90s", 90), ("1.5h", 5400), ("5", 300), (" 20 min ", 1200)])
def test_parse_duration(text, seconds):
    assert parse_duration(text) == seconds


@pytest.mark.parametrize("text", ["", "ten minutes", "-5m", "0", "5d"])
def test_exception_parse_duration(text):
    with pytest.raises(InputError, match="budget"):
        parse_duration(text)


def test_all_table_in_config_file(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text('[all]\nbudget = "10m"\n')
    assert load_config_file(good)["all"] == {"budget": "10m"}
    bad = tmp_path / "bad.toml"
    bad.write_text("[all]\nbudget = 10\n")
    with pytest.raises(InputError, match="all.budget"):
        load_config_file(bad)


def test_working_size_line_and_gpu_rule(monkeypatch):
    monkeypatch.setattr("wgs.estimate.cached_calibration", lambda device: CAL)
    k, line = RunTiming(torch.device("cpu"), configs())(4000, 3000, 4, 8, True)
    assert 4000 // k <= 400 and line.startswith(f"working size: {4000 // k}x{3000 // k}")
    assert "--max-size" in line
    k, line = RunTiming(torch.device("cpu"), configs())(64, 64, 4, 8, True)
    assert k == 1 and "own size" in line
    k, line = RunTiming(torch.device("cuda"), configs())(4000, 3000, 4, 8, True)
    assert k == 3 and "1600" in line


def test_feature_prepare_max_size_and_estimate(blender_scene, tmp_path):
    """`wgs prepare --max-size` sets the working size; without it the machine's is chosen and said;
    the estimate of what follows is printed and kept in run.json."""
    ws = tmp_path / "ws"
    r = run_wgs(["-w", str(ws), "prepare", str(blender_scene), "--views", "4", "--max-size", "32"], tmp_path)
    assert r.returncode == 0, r.stderr
    info = json.loads((ws / "scene" / "scene.json").read_text())
    assert max(info["resolution"]) <= 32 and info["downscale"] >= 2
    assert "working size:" in r.stderr and "--max-size 32" in r.stderr
    assert "estimate: about" in r.stderr
    record = json.loads((ws / "run.json").read_text())
    assert set(record["estimate"]) >= {"coarse", "fine", "eval"} and record["budget_s"] is None
    ws2 = tmp_path / "ws2"
    r = run_wgs(["-w", str(ws2), "prepare", str(blender_scene), "--views", "4"], tmp_path)
    assert r.returncode == 0 and "own size" in r.stderr


def test_exception_bad_budget(blender_scene, tmp_path):
    expect_error(tmp_path, ["-w", str(tmp_path / "ws"), "all", str(blender_scene), "--budget", "soon"], "budget")


def test_feature_report_puts_the_estimate_beside_the_time(finished_workspace):
    base, _ = finished_workspace
    ws = base / "ws"
    record = json.loads((ws / "run.json").read_text())
    assert set(record["estimate"]) == {"coarse", "mask_data", "finetune", "repair", "fine", "eval"}
    report = (ws / "6_eval" / "report.md").read_text()
    assert "| stage | wall time (s) | estimate (s) |" in report
    coarse_row = next(line for line in report.splitlines() if line.startswith("| coarse |"))
    assert float(coarse_row.split("|")[3]) == pytest.approx(record["estimate"]["coarse"], abs=0.05)
    results = json.loads((ws / "6_eval" / "results.json").read_text())
    assert results["estimate_s"] == record["estimate"] and results["budget_s"] is None
    assert "estimate (s)" in (ws / "6_eval" / "report.html").read_text()


def test_feature_budget_time_boxes_the_training_stages(tmp_path, monkeypatch):
    """With a budget, after prepare the training stages are time-boxed to fill what is left; a rerun
    with the same budget keeps the plan, so that the finished stages stay up to date."""
    from wgs.workspace import Workspace

    monkeypatch.setattr("wgs.estimate.cached_calibration", lambda device: CAL)
    ws = Workspace(tmp_path / "ws")
    ws.root.mkdir()
    info = {"resolution": [200, 200], "train_names": ["a"] * 4, "test_names": ["b"] * 8, "has_masks": True}
    runs = ("prepare", "coarse", "mask_data", "finetune", "repair", "fine", "eval")
    timing = RunTiming(torch.device("cpu"), configs(), budget_s=600.0)
    cfgs = timing.after_prepare(ws, info, runs)
    record = json.loads((ws.root / "run.json").read_text())
    assert record["budget_s"] == 600.0
    assert sum(record["plan"]["seconds"].values()) == pytest.approx(600.0 - 3.0, rel=0.02)
    for t in ("coarse", "mask_data", "fine"):
        assert cfgs[t].max_seconds == record["plan"]["stages"][t]["max_seconds"] > 0
    assert record["estimate"]["coarse"] == pytest.approx(record["plan"]["seconds"]["coarse"], rel=0.01)
    # a rerun finds the same plan in run.json once its stages have run with it
    again = RunTiming(torch.device("cpu"), configs(), budget_s=600.0)
    monkeypatch.setattr("wgs.estimate._fresh", lambda ws, table, cfg, fields=None: True)
    assert again.after_prepare(ws, info, runs)["coarse"].max_seconds == cfgs["coarse"].max_seconds


def test_every_stage_has_a_cost_model():
    """Each config table in the registry is modelled, the on-request baseline too (it trains as long
    as the method's stages from coarse to fine)."""
    model = stage_seconds(CAL, configs(), SceneFacts(128, 128, 4, 8))
    assert set(model) == set(STAGES)
    method = sum(model[t] for t in ("coarse", "mask_data", "finetune", "repair", "fine"))
    assert method < model["baseline"] < method + 2.0


def test_a_stage_without_a_cost_model_is_estimated_as_unknown(tmp_path, monkeypatch):
    """A stage the cost model lacks cannot crash a run: the line names it as unknown, its sum leaves it out."""
    from wgs.estimate import estimate_line, per_stage
    from wgs.workspace import Workspace

    assert per_stage({"coarse": 60.0}, ("coarse", "baseline")) == {"coarse": 60.0, "baseline": None}
    line = estimate_line({"coarse": 60.0, "baseline": None})
    assert line.startswith("estimate: about 60 s on this machine and baseline unknown (no cost model)")
    partial = stage_seconds  # the cost model without the baseline, as a new stage would be
    monkeypatch.setattr(
        "wgs.estimate.stage_seconds", lambda *a: {k: v for k, v in partial(*a).items() if k != "baseline"}
    )
    timing = RunTiming(torch.device("cpu"), configs())
    timing._cal = CAL
    ws = Workspace(tmp_path / "ws")
    info = {"resolution": [64, 64], "train_names": ["a"] * 4, "test_names": ["b"] * 4, "has_masks": True}
    timing.after_prepare(ws, info, ("prepare", "coarse", "baseline"))
    estimate = ws.run_record()["estimate"]
    assert estimate["baseline"] is None and estimate["coarse"] > 0


def test_budget_with_the_baseline_halves_the_training():
    """The baseline trains as long again as coarse to fine: a budget that includes it gives the
    method's training stages about half the time."""
    facts = SceneFacts(200, 200, 4, 8)
    runs = ("coarse", "mask_data", "finetune", "repair", "fine", "eval")
    alone = budget_plan(CAL, configs(), facts, 1200.0, runs)["seconds"]
    both = budget_plan(CAL, configs(), facts, 1200.0, (*runs, "baseline"))["seconds"]
    assert sum(alone.values()) == pytest.approx(1200.0, rel=0.02)
    assert sum(both.values()) == pytest.approx(1200.0, rel=0.02)
    assert both["coarse"] < 0.55 * alone["coarse"]
    assert "baseline" in both and "baseline" not in alone


def test_working_size_counts_the_masks_share(monkeypatch):
    """An object that fills its photos costs more per pixel (`cover_factor`): the chooser, told the
    given masks' share, picks a smaller working size for it than for the same photos with the share
    of the fit, and without a share it models that of the fit."""
    monkeypatch.setattr("wgs.estimate.cached_calibration", lambda device: CAL)
    timing = RunTiming(torch.device("cpu"), configs())
    k_fit, _ = timing(1600, 1200, 4, 8, True, FIT_MASK_SHARE)
    k_close, line = timing(1600, 1200, 4, 8, True, 0.75)
    assert k_close > k_fit
    assert timing(1600, 1200, 4, 8, True, None)[0] == k_fit
    assert line.startswith(f"working size: {1600 // k_close}x{1200 // k_close}")
    assert "the object covers 75 % of the photos" in line


def test_working_size_counts_the_baseline_when_asked():
    facts = SceneFacts(1600, 1200, 4, 8, full_pixels=1600 * 1200)
    k_alone, _ = choose_downscale(CAL, configs(), facts, 600.0)
    k_both, total = choose_downscale(CAL, configs(), facts, 600.0, (*STAGES, "baseline"))
    assert k_both >= k_alone and total is not None


def test_the_estimate_counts_the_stages_a_change_makes_stale_downstream(finished_workspace, tmp_path, monkeypatch):
    """A finished run: with finetune's config changed, the estimate counts finetune and every stage
    that reads it (repair, fine, eval), not finetune alone; with the scene re-imported (the coarse
    stage's recorded input no longer the scene's), every stage after prepare."""
    import shutil

    from wgs.workspace import Workspace

    monkeypatch.setattr("wgs.estimate.cached_calibration", lambda device: CAL)
    shutil.copytree(finished_workspace[0] / "ws", tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    info = json.loads((ws.root / "scene" / "scene.json").read_text())
    runs = ("prepare", "coarse", "mask_data", "finetune", "repair", "fine", "eval")

    def pending() -> tuple[str, ...]:
        timing = RunTiming(torch.device("cpu"), configs())
        timing.after_prepare(ws, info, runs)
        return timing.pending

    monkeypatch.setattr("wgs.estimate._fresh", lambda ws, table, cfg, fields=None: table != "finetune")
    assert pending() == ("finetune", "repair", "fine", "eval")
    assert set(json.loads((ws.root / "run.json").read_text())["estimate"]) == {"finetune", "repair", "fine", "eval"}
    monkeypatch.setattr("wgs.estimate._fresh", lambda ws, table, cfg, fields=None: True)
    assert pending() == ()
    manifest = ws.stage_dir("coarse") / "manifest.json"
    m = json.loads(manifest.read_text())
    m["upstream"]["prepare"] = "an earlier import"
    manifest.write_text(json.dumps(m))
    assert pending() == runs[1:]
