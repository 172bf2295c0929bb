"""`wgs ablate` on a tiny scene: every row, finite numbers, the coarse stage shared."""

import csv
import json
import math

import pytest
from click.testing import CliRunner
from conftest import TINY_ONE_MODEL, make_scene

from wgs.ablation import ROWS, pareto, parse_rows
from wgs.cli import cli
from wgs.workspace import Workspace


@pytest.mark.slow
def test_ablate_all_rows(tmp_path):
    scene = make_scene(tmp_path / "scene", seed=5, size=48, n_train=4, n_test=3)
    cfg = tmp_path / "wgs.toml"
    cfg.write_text(TINY_ONE_MODEL)
    root = tmp_path / "abl"
    res = CliRunner().invoke(
        cli,
        ["-q", "--config", str(cfg), "-w", str(root), "ablate", str(scene), "--rows", "all"],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    data = json.loads((root / "ablation.json").read_text())
    names = [r["row"] for r in data["rows"]]
    assert sorted(names) == sorted(ROWS)
    for r in data["rows"]:
        for k in ("psnr", "ssim", "time_s"):
            assert math.isfinite(r[k]), (r["row"], k)
        assert r["lpips"] is None  # no LPIPS weights in the test environment
        assert r["stage_times_s"]
    with open(root / "ablation.csv") as fh:
        assert len(list(csv.DictReader(fh))) == len(ROWS)
    assert (root / "ablation.png").stat().st_size > 1000
    md = (root / "ablation.md").read_text()
    assert "orm-wavelet-u" in md and "time(orm-wavelet-u) / time(loo-rgb)" in md
    # one coarse stage, shared by every row (the same manifest, copied)
    shared = Workspace(root / "_shared").manifest("coarse")["finished"]
    for name in ROWS:
        if name != "3dgs":
            assert Workspace(root / name).manifest("coarse")["finished"] == shared
    # orm pairs computed once for all ORM rows
    orm = Workspace(root / "_mask_orm").manifest("mask_data")["fingerprint"]
    assert Workspace(root / "orm-rgb").manifest("mask_data")["fingerprint"] == orm
    assert Workspace(root / "orm-wavelet-u-j2").manifest("finetune")["levels"] == 2
    # the prior row starts from the shipped prior, the paper's rows from scratch; both report the repair gain
    assert Workspace(root / "orm-wavelet-u-prior").manifest("finetune")["prior"].endswith("weights")
    assert Workspace(root / "orm-wavelet-u").manifest("finetune")["prior"] is None
    by = {r["row"]: r for r in data["rows"]}
    assert math.isfinite(by["orm-wavelet-u-prior"]["repair_gain_db"]) and by["3dgs"]["repair_gain_db"] is None
    assert "PSNR(orm-wavelet-u-prior) - PSNR(orm-wavelet-u)" in md
    # the carving row differs from the prior row only from the repair on: it carves, the other does not
    assert Workspace(root / "orm-wavelet-u-prior-carve").manifest("repair").get("carving") is not None
    assert Workspace(root / "orm-wavelet-u-prior").manifest("repair").get("carving") is None


def test_parse_rows_and_pareto():
    assert [r.name for r in parse_rows("3dgs")] == ["orm-wavelet-u-prior", "3dgs"]
    assert [r.name for r in parse_rows("paper")][-1] == "3dgs"
    rows = [
        {"row": "a", "psnr": 20.0, "time_s": 10.0},
        {"row": "b", "psnr": 21.0, "time_s": 20.0},
        {"row": "c", "psnr": 19.0, "time_s": 30.0},
    ]
    assert pareto(rows) == {"a", "b"}
    import pytest

    from wgs.errors import InputError

    with pytest.raises(InputError, match="unknown ablation row"):
        parse_rows("nope")
