"""mask-data and finetune stages on a tiny generated scene."""

import json

import pytest
import torch
from click.testing import CliRunner

from wgs.cli import cli
from wgs.io.exr import read_subbands
from wgs.models.storage import load_model
from wgs.scene.dataset import load_prepared
from wgs.stages.shared import subband_file
from wgs.weights import WEIGHTS as PRIOR_WEIGHTS
from wgs.workspace import Workspace

TRAIN = ["--preset", "fast", "--iterations", "40"]


def invoke(*args):
    res = CliRunner().invoke(cli, ["-q", *args], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def coarse_ws(blender_scene, tmp_path_factory):
    ws = Workspace(tmp_path_factory.mktemp("md") / "ws")
    invoke("-w", str(ws.root), "prepare", str(blender_scene))
    invoke("-w", str(ws.root), "coarse", *TRAIN)
    return ws


def copy_ws(ws, dst):
    import shutil

    shutil.copytree(ws.root, dst)
    return Workspace(dst)


def mask_data(ws, tmp_path, *extra):
    cfg = tmp_path / "wgs.toml"
    cfg.write_text("[mask_data]\nwarmup = 20\npair_every = 10\n")
    invoke("--config", str(cfg), "-w", str(ws.root), "mask-data", *TRAIN, *extra)


@pytest.mark.parametrize("strategy", ["orm", "offline-rm", "loo"])
def test_mask_data_pairs_and_index(coarse_ws, tmp_path, strategy):
    ws = copy_ws(coarse_ws, tmp_path / "ws")
    mask_data(ws, tmp_path, "--strategy", strategy)
    d = ws.stage_dir("mask_data")
    index = json.loads((d / "index.json").read_text())
    n_views = 4
    per_model = len(range(20, 41, 10))  # iterations 20, 30, 40
    assert len(index["pairs"]) == n_views * per_model  # orm: 4 views per snapshot; loo: 1 view x 4 models
    listed = {p["ll"] for p in index["pairs"]} | {p["rgb"] for p in index["pairs"]}
    on_disk = {str(p.relative_to(d)) for p in (d / "pairs").rglob("*.exr")}
    assert listed == on_disk  # the index lists what exists and nothing else
    p = index["pairs"][0]
    ll = read_subbands(d / p["ll"])
    assert set(ll) == {"LL", "cLL", "M"} and ll["LL"].shape == (24, 24, 3) and ll["M"].shape == (24, 24, 1)
    rgb = read_subbands(d / p["rgb"])
    assert rgb["RGB"].shape == (48, 48, 3)
    hidden = float(rgb["M"].mean())
    assert (hidden == 0.0) if strategy == "loo" else (0.1 < hidden < 0.6)
    assert index["hf_views"] == [f.name for f in load_prepared(ws.output("prepare", "prepared")).colour_views]
    assert all(subband_file(ws, kind, v).is_file() for v in index["hf_views"] for kind in ("render", "ref"))
    m = ws.manifest("mask_data")
    assert m["strategy"] == strategy and m["models"] == (4 if strategy == "loo" else 1)
    assert m["strategy_seconds"] > 0


def test_finetune_trains_and_saves_d_and_u(coarse_ws, tmp_path):
    ws = copy_ws(coarse_ws, tmp_path / "ws")
    mask_data(ws, tmp_path)
    cfg = tmp_path / "finetune.toml"
    # a short fine-tune of the prior, evaluated three times
    cfg.write_text("[finetune]\nprior_steps = 12\nprior_eval_every = 4\n")
    invoke(
        "--config",
        str(cfg),
        "-w",
        str(ws.root),
        "finetune",
        "--preset",
        "fast",
        "--d-steps",
        "30",
        "--u-max-steps",
        "30",
    )
    d = ws.stage_dir("finetune")
    D, cfg = load_model(d / "D")
    assert cfg["domain"] == "wavelet"
    # the default starts from the shipped prior: D repairs in one step from the render
    assert cfg["start"] == "corrupted" and ws.manifest("finetune")["prior"].endswith("weights")
    curves = json.loads((d / "curves.json").read_text())
    assert len(curves["D"]["loss"]) > 0 and "val" in curves["U"]
    assert (d / "curves.png").stat().st_size > 1000
    m = ws.manifest("finetune")
    # U is trained, and kept only where it beats no HF repair on the held-out crops
    assert m["u_used"] == curves["U"]["beats_identity"] == (m["u_best_val"] < m["u_identity_val"])
    assert (d / "U").is_dir() == m["u_used"]
    if m["u_used"]:
        load_model(d / "U")
    for k in ("l1_before", "l1_after", "psnr_before", "psnr_after"):
        assert torch.isfinite(torch.tensor(m["heldout"][k]))
    # no fine-tune steps: D is the prior as shipped, its held-out error the curve's one point
    invoke("-w", str(ws.root), "finetune", "--preset", "fast", "--prior-steps", "0", "--u-max-steps", "10")
    shipped = load_model(PRIOR_WEIGHTS / "D")[0].state_dict()
    assert all(torch.equal(v, shipped[k]) for k, v in load_model(d / "D")[0].state_dict().items())
    curves = json.loads((d / "curves.json").read_text())
    assert curves["D"]["step"] == [] and curves["D"]["stopped_at"] == 0 and curves["D"]["bar"] > 0
    assert ws.manifest("finetune")["d_stopped_at"] == 0 and (d / "curves.png").stat().st_size > 1000
    # --prior none: the from-scratch denoising D (SDEdit at repair time), its own width
    invoke(
        "-w", str(ws.root), "finetune", "--preset", "fast", "--d-steps", "10", "--u-max-steps", "10", "--prior", "none"
    )
    cfg = load_model(d / "D")[1]
    assert cfg["start"] == "clean" and cfg["channels"] == 16 and ws.manifest("finetune")["prior"] is None
    # RGB-domain D for the ablation: no U
    invoke("-w", str(ws.root), "finetune", "--preset", "fast", "--d-steps", "10", "--domain", "rgb")
    assert not (d / "U").exists() and load_model(d / "D")[1]["domain"] == "rgb"


def test_finetune_needs_mask_data(coarse_ws, tmp_path):
    ws = copy_ws(coarse_ws, tmp_path / "ws")
    res = CliRunner().invoke(cli, ["-w", str(ws.root), "finetune"])
    assert res.exit_code != 0 and "mask-data" in str(res.exception)
