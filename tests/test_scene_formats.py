"""Scene import: every format gives the same cameras; projection agrees with pycolmap."""

import numpy as np
import pytest
from click.testing import CliRunner

from wgs.cli import cli
from wgs.io import read_json
from wgs.io.images import downscale
from wgs.scene.colmap import project_point
from wgs.scene.convention import Normalisation
from wgs.scene.dataset import load_prepared
from wgs.scene.formats import read_scene
from wgs.scene.idr import decompose_projection
from wgs.workspace import Workspace


def prepare(scene, ws, *args):
    """`wgs prepare` without mirror views: these tests compare the photos' own cameras."""
    res = CliRunner().invoke(
        cli, ["-q", "-w", str(ws), "prepare", str(scene), "--mirror", "none", *args], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    return Workspace(ws)


def world_poses(ws: Workspace):
    """{view index in sorted order: w2c in the source's world} from the prepared model."""
    sc = load_prepared(ws.stage_dir("prepare"), load_test_images=True)
    return sc, [sc.norm.w2c_from_normalised(f.viewmat.double().numpy()) for f in sc.train + sc.test]


@pytest.mark.parametrize("fmt", ["blender", "colmap", "ngp", "idr"])
def test_formats_round_trip(scene_formats, tmp_path, fmt):
    src = scene_formats[fmt]
    ref = read_scene(scene_formats["blender"])
    ws = prepare(src, tmp_path / "ws", "--views", "4")
    info = read_json(ws.stage_dir("prepare") / "scene.json")
    assert info["format"] == fmt
    assert info["has_masks"] is True
    assert len(info["train_names"]) == 4
    sc, poses = world_poses(ws)
    # every prepared camera equals one of the Blender cameras (same world, same intrinsics)
    ref_poses = [v.w2c for v in ref.views]
    for f, w2c in zip(sc.train + sc.test, poses, strict=True):
        err = min(np.abs(w2c - r).max() for r in ref_poses)
        assert err < 1e-5, (f.name, err)
        np.testing.assert_allclose(f.K.numpy(), ref.views[0].K, rtol=1e-5)
    assert set(info["train_names"]).isdisjoint(info["test_names"])
    for f in sc.train:
        assert f.image.shape == (48, 48, 3) and f.mask.shape == (48, 48)


def test_projection_matches_pycolmap(blender_scene, tmp_path):
    ws = prepare(blender_scene, tmp_path / "ws")
    sc = load_prepared(ws.stage_dir("prepare"))
    rng = np.random.default_rng(0)
    for f in sc.train:
        for X in rng.normal(scale=0.3, size=(5, 3)):
            cam = f.viewmat.double().numpy() @ np.append(X, 1.0)
            uv = (f.K.double().numpy() @ cam[:3])[:2] / cam[2]
            ref = project_point(ws.stage_dir("prepare") / "sparse", f.name, X)
            np.testing.assert_allclose(uv, ref, atol=1e-3)


def test_normalisation_uses_training_cameras_only(blender_scene, tmp_path):
    a = read_json(prepare(blender_scene, tmp_path / "a", "--views", "3").stage_dir("prepare") / "scene.json")
    b = read_json(prepare(blender_scene, tmp_path / "b", "--views", "3").stage_dir("prepare") / "scene.json")
    assert a["normalisation"] == b["normalisation"]
    n = Normalisation.from_json(a["normalisation"])
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1, 0.2, 3.0]
    np.testing.assert_allclose(n.w2c_from_normalised(n.w2c_to_normalised(w2c)), w2c, atol=1e-12)


def test_lego_done_when(tmp_path):
    from conftest import lego_or_skip

    lego = lego_or_skip()
    ws = prepare(lego, tmp_path / "ws", "--views", "4", "--downscale", "2")
    res = CliRunner().invoke(cli, ["-w", str(ws.root), "info"])
    assert res.exit_code == 0
    assert "4 training views, 200 test views, 200x200 images, with masks" in " ".join(res.output.split())
    info = read_json(ws.stage_dir("prepare") / "scene.json")
    assert info["train_images"][0].startswith("train/") and len(info["test_images"]) == 200


def test_prepare_skips_when_fresh(blender_scene, tmp_path):
    ws = prepare(blender_scene, tmp_path / "ws")
    t = ws.manifest("prepare")["finished"], (ws.stage_dir("prepare") / "manifest.json").stat().st_mtime_ns
    prepare(blender_scene, tmp_path / "ws")
    assert (ws.stage_dir("prepare") / "manifest.json").stat().st_mtime_ns == t[1]
    prepare(blender_scene, tmp_path / "ws", "--downscale", "2")  # new config: redone
    assert (ws.stage_dir("prepare") / "manifest.json").stat().st_mtime_ns != t[1]


def test_downscale_premultiplied_keeps_edges_clean():
    rgb = np.zeros((2, 2, 3), np.float32)
    rgb[0, 0] = [1, 0, 0]  # red object pixel; the other pixels are transparent black
    mask = np.array([[1, 0], [0, 0]], np.float32)
    out, a = downscale(rgb, mask, 2)
    np.testing.assert_allclose(out[0, 0], [1, 0, 0])  # no darkening from the transparent pixels
    np.testing.assert_allclose(a[0, 0], 0.25)


def test_decompose_projection():
    rng = np.random.default_rng(3)
    K = np.array([[300.0, 0.5, 60], [0, 280, 50], [0, 0, 1]])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    t = rng.normal(size=3)
    P = -7.0 * K @ np.hstack([R, t[:, None]])
    K2, w2c = decompose_projection(P)
    np.testing.assert_allclose(K2, K, atol=1e-9)
    np.testing.assert_allclose(w2c[:3, :3], R, atol=1e-9)
    np.testing.assert_allclose(w2c[:3, 3], t, atol=1e-9)


def test_colmap_distorted_is_undistorted(scene_formats, tmp_path):
    """An OPENCV camera is undistorted through pycolmap into a pinhole model."""
    import shutil

    import pycolmap

    d = tmp_path / "colmap"
    shutil.copytree(scene_formats["colmap"], d)
    rec = pycolmap.Reconstruction(str(d / "sparse" / "0"))
    for cam in rec.cameras.values():
        fx, fy, cx, cy = cam.params
        rec.cameras[cam.camera_id] = pycolmap.Camera(
            camera_id=cam.camera_id,
            model="OPENCV",
            width=cam.width,
            height=cam.height,
            params=[fx, fy, cx, cy, 0.05, 0, 0, 0],
        )
    rec.write_text(str(d / "sparse" / "0"))
    ws = prepare(d, tmp_path / "ws")
    sc = load_prepared(ws.stage_dir("prepare"))
    f = sc.train[0]
    assert f.image.shape[:2] == (f.height, f.width) and f.mask is not None
    assert abs(f.width - 48) <= 4


def test_colmap_uses_images_k(scene_formats, tmp_path):
    import shutil

    from wgs.io.images import read_image, write_png

    d = tmp_path / "colmap"
    shutil.copytree(scene_formats["colmap"], d)
    for p in (d / "images").iterdir():
        write_png(d / "images_2" / p.name, np.full((24, 24, 3), 0.25, np.float32))  # recognisable
    ws = prepare(d, tmp_path / "ws", "--downscale", "2")
    first = load_prepared(ws.stage_dir("prepare")).train[0]
    img = read_image(ws.stage_dir("prepare") / "images" / first.name)
    assert img.shape[:2] == (24, 24) and abs(float(img.mean()) - 0.25) < 0.01
    assert abs(first.K[0, 0].item() - 0.5 * read_scene(d).views[0].K[0, 0]) < 1e-4
