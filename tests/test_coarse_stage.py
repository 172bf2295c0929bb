"""The coarse stage end to end on a tiny generated scene, through the CLI."""

import json

import torch
from click.testing import CliRunner

from wgs.cli import cli
from wgs.gaussians.splats import import_ply, load_checkpoint
from wgs.io.exr import read_subbands
from wgs.wavelet.haar import dwt2
from wgs.workspace import Workspace

TINY = ["--iterations", "60"]


def invoke(*args):
    res = CliRunner().invoke(cli, ["-q", *args], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res


def test_coarse_writes_the_workspace_contract(blender_scene, tmp_path):
    ws = Workspace(tmp_path / "ws")
    invoke("-w", str(ws.root), "prepare", str(blender_scene))
    invoke("-w", str(ws.root), "coarse", "--preset", "fast", *TINY)
    d = ws.stage_dir("coarse")
    m = ws.manifest("coarse")
    assert m["iterations"] == 60 and m["num_gaussians"] > 0 and m["train_psnr"] > 10
    names = (ws.stage_dir("prepare") / "split_train.txt").read_text().split()
    for n in names:
        stem = n.rsplit(".", 1)[0]
        assert (d / "renders" / n).is_file()
        ref = read_subbands(d / "subbands" / "ref" / f"{stem}.exr")
        ren = read_subbands(d / "subbands" / "render" / f"{stem}.exr")
        assert list(ref) == ["LL", "LH", "HL", "HH"] and ref["LL"].shape == (24, 24, 3)
        assert ren["LL"].shape == ref["LL"].shape
    # the stored LL of a reference is the DWT of that reference composited on white
    from wgs.scene.dataset import composite, load_prepared

    sc = load_prepared(ws.stage_dir("prepare"))
    f = sc.train[0]
    ref_img = composite(f.image, f.mask, torch.ones(3))
    ll, _ = dwt2(ref_img.permute(2, 0, 1)[None], 1)
    got = read_subbands(d / "subbands" / "ref" / f"{f.name.rsplit('.', 1)[0]}.exr")["LL"]
    assert (torch.from_numpy(got) - ll[0].permute(1, 2, 0)).abs().max() < 2e-3  # half precision
    splats, blob = load_checkpoint(d / "ckpt.pt", sc.norm)
    ply = import_ply(d / "point_cloud.ply")
    assert ply["means"].shape[0] == splats["means"].shape[0] == m["num_gaussians"]
    torch.testing.assert_close(ply["means"], blob["splats"]["means"])  # PLY is in world coordinates
    assert ply["shN"].shape[1] == 15  # padded to degree 3 (45 f_rest) for INRIA-layout viewers
    deg = blob["splats"]["shN"].shape[1]
    torch.testing.assert_close(ply["shN"][:, :deg], blob["splats"]["shN"])
    assert (ply["shN"][:, deg:] == 0).all()
    assert json.loads((d / "train_psnr.json").read_text()).keys() == set(names)

    # fresh: skipped; a new option reruns coarse
    before = (d / "manifest.json").stat().st_mtime_ns
    invoke("-w", str(ws.root), "coarse", "--preset", "fast", *TINY)
    assert (d / "manifest.json").stat().st_mtime_ns == before
    invoke("-w", str(ws.root), "coarse", "--preset", "fast", "--iterations", "30")
    assert ws.manifest("coarse")["iterations"] == 30

    invoke("-w", str(ws.root), "render", "--views", "path", "--frames", "3")
    assert len(list((ws.root / "renders" / "coarse_path").iterdir())) == 3
    res = invoke("-w", str(ws.root), "info")
    assert "fresh" in res.output


def test_coarse_without_prepare_is_a_clear_error(tmp_path):
    res = CliRunner().invoke(cli, ["-w", str(tmp_path / "ws"), "coarse"])
    assert res.exit_code != 0 and "wgs prepare" in str(res.exception)


def test_config_file_sets_stage_options(blender_scene, tmp_path):
    cfg = tmp_path / "wgs.toml"
    cfg.write_text("seed = 3\n[coarse]\niterations = 20\nsh_degree = 0\n")
    ws = Workspace(tmp_path / "ws")
    invoke("--config", str(cfg), "-w", str(ws.root), "prepare", str(blender_scene))
    invoke("--config", str(cfg), "-w", str(ws.root), "coarse", "--preset", "fast")
    m = ws.manifest("coarse")
    assert m["iterations"] == 20 and m["config"]["sh_degree"] == 0 and m["seed"] == 3
    invoke("--config", str(cfg), "-w", str(ws.root), "coarse", "--iterations", "25")  # CLI beats the file
    assert ws.manifest("coarse")["iterations"] == 25


def test_the_tests_config_files_are_valid_toml(tmp_path, monkeypatch):
    """The configs the suite builds from TINY, the cluster tests' too (which `make test` does not
    collect), parse as wgs config files: a key set twice fails here first."""
    import importlib.util
    from pathlib import Path

    import conftest
    import test_resume

    from wgs.config import load_config_file

    folder = Path(__file__).parent / "cluster"
    monkeypatch.syspath_prepend(str(folder))  # its local_slurm
    spec = importlib.util.spec_from_file_location("cluster_batch", folder / "test_slurm_batch.py")
    assert spec is not None and spec.loader is not None
    cluster = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cluster)
    texts = [conftest.TINY, conftest.TINY_ONE_MODEL, conftest.TINY_HELD_OUT, test_resume.CFG, cluster.LONG_COARSE]
    for i, text in enumerate(texts):
        (tmp_path / f"c{i}.toml").write_text(text)
        assert load_config_file(tmp_path / f"c{i}.toml")["coarse"]


def test_the_ensemble_starts_its_longest_models_first():
    """Lego's stop (1200 of 1500) and its pilots' ends: G_c (its first 30 % at half size), then the
    sixth model (60 %, from the start), then the members carried on from the pilots, least far first."""
    from wgs.stages.coarse.run import longest_first
    from wgs.stages.coarse.settings import CoarseConfig

    cfg = CoarseConfig(end_iteration=1200)
    assert longest_first(cfg, [0, 675, 675, 600, 425, 0]) == [0, 5, 4, 3, 1, 2]
    assert longest_first(CoarseConfig(ensemble=3), [0, 0, 0]) == [0, 1, 2]  # ties keep their order
