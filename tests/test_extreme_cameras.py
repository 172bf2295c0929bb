"""Stability suite, cameras: normalisation of scenes in millimetres .. kilometres, nearly collinear
training cameras.

Every case and its pass criterion is listed in docs/stability.md."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import ring_w2c

from wgs.cli import cli
from wgs.gaussians.splats import load_checkpoint
from wgs.scene.convention import normalisation_from_cameras
from wgs.scene.orbit import look_at


@pytest.mark.parametrize("unit", [1e-3, 1.0, 1e4])
def test_normalisation_is_scale_invariant(unit):
    """Scenes in millimetres or kilometres normalise to the same cameras (up to float rounding)."""
    base = ring_w2c(jitter=0.2)
    scaled = []
    for m in base:
        s = m.copy()
        s[:3, 3] *= unit
        scaled.append(s)
    a, b = normalisation_from_cameras(base), normalisation_from_cameras(scaled)
    assert b.scale == pytest.approx(a.scale * unit, rel=1e-9)
    for m, s in zip(base, scaled, strict=True):
        np.testing.assert_allclose(b.w2c_to_normalised(s), a.w2c_to_normalised(m), atol=1e-9)


def test_nearly_collinear_cameras_give_a_finite_centre():
    """All cameras on one line, looking the same way: the axes barely intersect; the centre stays finite."""
    ws = []
    for i in range(4):
        eye = np.array([i * 1e-3, 0.0, -2.0])
        ws.append(look_at(eye, eye + np.array([1e-6 * i, 0, 1.0]), np.array([0.0, -1.0, 0.0])))
    n = normalisation_from_cameras(ws)
    assert np.isfinite(n.center).all() and np.isfinite(n.scale) and n.scale > 0


UNITS_CONFIG = "[coarse]\niterations = 40\ninit_points = 600\nhull_resolution = 24\nensemble = 1\n"


def prepared_and_coarse(scene: Path, root: Path) -> tuple[float, dict]:
    """`wgs prepare` + `wgs coarse` (in this process) -> G_c's training PSNR and its Gaussians."""
    cfg = root / "wgs.toml"
    cfg.write_text(UNITS_CONFIG)
    for args in (["prepare", scene], ["coarse"]):
        res = CliRunner().invoke(cli, ["-q", "--config", str(cfg), "-w", str(root / "ws"), *map(str, args)])
        assert res.exit_code == 0, res.output
    splats, _ = load_checkpoint(root / "ws" / "1_coarse" / "ckpt.pt")
    return json.loads((root / "ws" / "1_coarse" / "manifest.json").read_text())["train_psnr"], splats


@pytest.fixture(scope="module")
def in_scene_units(blender_scene, tmp_path_factory) -> tuple[float, dict]:
    return prepared_and_coarse(blender_scene, tmp_path_factory.mktemp("units"))


@pytest.mark.slow
@pytest.mark.parametrize("unit", [1e-3, 1e4])
def test_scene_in_other_units_trains_to_the_same_model_up_to_scale(blender_scene, in_scene_units, tmp_path, unit):
    """The tiny scene with every camera position multiplied by `unit` (radius ~3e-3 .. 3e4): prepare +
    coarse give the same training PSNR and the same Gaussians, scaled by `unit`."""
    scaled = tmp_path / "scaled"
    shutil.copytree(blender_scene, scaled)
    for split in ("train", "test"):
        path = scaled / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for f in meta["frames"]:
            for r in range(3):
                f["transform_matrix"][r][3] *= unit
        path.write_text(json.dumps(meta))
    (psnr_a, a), (psnr_b, b) = in_scene_units, prepared_and_coarse(scaled, tmp_path)
    assert psnr_b == pytest.approx(psnr_a, abs=0.05)
    assert a["means"].shape == b["means"].shape
    torch.testing.assert_close(b["means"] / unit, a["means"], atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(b["scales"] - math.log(unit), a["scales"], atol=2e-3, rtol=1e-3)
