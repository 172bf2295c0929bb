"""The coarse ensemble: members from other seeds, their repaired renders averaged into pseudo references."""

import torch
from click.testing import CliRunner
from conftest import expect_error

from wgs.cli import cli
from wgs.gaussians.splats import load_checkpoint
from wgs.gaussians.trainer import render_frame
from wgs.models.denoiser_meta import DenoiserMeta
from wgs.models.repair import Repairer
from wgs.scene.dataset import load_prepared
from wgs.stages.coarse import run as coarse_run
from wgs.stages.shared import coarse_members, ensemble_repair, member_file
from wgs.workspace import Workspace

TINY = ["--preset", "fast", "--iterations", "40"]


def invoke(*args, code=0):
    res = CliRunner().invoke(cli, ["-q", *map(str, args)])
    assert res.exit_code == code, res.output
    return res


def test_members_are_trained_from_other_seeds_and_averaged(blender_scene, tmp_path):
    ws = Workspace(tmp_path / "ws")
    invoke("-w", ws.root, "prepare", blender_scene)
    invoke("-w", ws.root, "coarse", *TINY, "--ensemble", "3")
    assert ws.manifest("coarse")["ensemble"] == 3 and len(ws.manifest("coarse")["member_seconds"]) == 2
    scene = load_prepared(ws.stage_dir("prepare"))
    members = coarse_members(ws, scene, torch.device("cpu"))
    assert len(members) == 3
    g_c = load_checkpoint(ws.output("coarse", "model"), scene.norm)[0]
    assert torch.equal(members[0]["means"], g_c["means"])
    m1 = load_checkpoint(ws.output("coarse", "members", member_file(1)), scene.norm)[0]
    assert not torch.equal(m1["means"][:100], g_c["means"][:100])  # another seed, another model

    # with an identity repair the pseudo reference is the mean of the members' renders
    bg, f, identity = torch.ones(3), scene.train[0], Repairer(lambda x: x, None, DenoiserMeta())
    renders = [render_frame(m, f, torch.device("cpu"), bg)[0] for m in members]
    first, ref, bands_in, bands_out = ensemble_repair(members, f, bg, identity, torch.device("cpu"))
    torch.testing.assert_close(first, renders[0])
    torch.testing.assert_close(ref, torch.stack(renders).mean(0), atol=1e-5, rtol=0)
    assert list(bands_out) == ["LL", "LH", "HL", "HH"]
    assert bands_in["LL"].shape == (f.height // 2, f.width // 2, 3)
    # one member: its own repair
    _, alone, _, _ = ensemble_repair(members[:1], f, bg, identity, torch.device("cpu"))
    torch.testing.assert_close(alone, renders[0], atol=1e-5, rtol=0)


def test_one_member_is_g_c_alone(blender_scene, tmp_path):
    ws = Workspace(tmp_path / "ws")
    invoke("-w", ws.root, "prepare", blender_scene)
    invoke("-w", ws.root, "coarse", *TINY, "--ensemble", "1")
    assert ws.manifest("coarse")["ensemble"] == 1
    assert not (ws.stage_dir("coarse") / "members").exists()
    assert len(coarse_members(ws, load_prepared(ws.stage_dir("prepare")), torch.device("cpu"))) == 1


def test_ensemble_below_one_is_refused(blender_scene, tmp_path):
    ws = tmp_path / "ws"
    invoke("-w", ws, "prepare", blender_scene)
    res = invoke("-w", ws, "coarse", *TINY, "--ensemble", "0", code=2)
    assert "ensemble" in res.output
    cfg = tmp_path / "wgs.toml"
    cfg.write_text("[coarse]\nensemble = 0\n")
    expect_error(tmp_path, ["--config", cfg, "-w", ws, "coarse", *TINY], "'ensemble' must be at least 1")
    assert not (ws / "1_coarse" / "manifest.json").exists()


def test_models_side_by_side_equal_the_one_thread_ones_in_order(blender_scene, tmp_path, monkeypatch):
    """Training the models in one-thread processes changes where they run, not what they are."""
    serial, side = Workspace(tmp_path / "serial"), Workspace(tmp_path / "side")
    for ws in (serial, side):
        invoke("-w", ws.root, "prepare", blender_scene)
    invoke("--threads", "1", "-w", serial.root, "coarse", *TINY, "--ensemble", "3")
    monkeypatch.setattr(coarse_run, "side_by_side", lambda models, iterations, pixels, on_cpu: 2)
    invoke("-w", side.root, "coarse", *TINY, "--ensemble", "3")  # (also resets the thread count)
    assert serial.manifest("coarse")["side_by_side"] == 1 and side.manifest("coarse")["side_by_side"] == 2
    for parts in (("model",), ("members", member_file(1)), ("members", member_file(2))):
        a = load_checkpoint(serial.output("coarse", *parts))[0]
        b = load_checkpoint(side.output("coarse", *parts))[0]
        assert all(torch.equal(a[k], b[k]) for k in a), parts
    assert (side.stage_dir("coarse") / "curve.json").is_file() == (serial.stage_dir("coarse") / "curve.json").is_file()


def test_side_by_side_only_on_the_cpu_and_for_work_worth_a_process():
    from wgs.threads import configured_count, side_by_side

    lego = 200 * 200
    assert side_by_side(8, 1500, lego, on_cpu=True) == min(8, configured_count())
    assert side_by_side(8, 1500, lego, on_cpu=False) == 1
    assert side_by_side(2, 30, 64 * 64, on_cpu=True) == 1
    assert side_by_side(1, 1500, lego, on_cpu=True) == 1
