"""Own photos: structure-from-motion (pycolmap) on photos we render, LLFF captures, split choice,
pose errors after a similarity alignment."""

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import expect_error, ring_w2c, run_wgs
from photo_scene import make_photos

from wgs.errors import InputError
from wgs.io.images import read_image, write_png
from wgs.scene.colmap import read_colmap_scene
from wgs.scene.formats import detect_format, read_scene
from wgs.scene.llff import llff_to_w2c
from wgs.scene.pose_error import camera_similarity, centers, pose_errors, umeyama
from wgs.scene.sfm import find_photos, pose_photos
from wgs.scene.splits import choose_split
from wgs.scene.types import RawScene, View


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """20 photos of a textured object on a ring, with masks; the true cameras."""
    root = tmp_path_factory.mktemp("photos")
    return root, make_photos(root, n=20)


def estimated_vs_true(model: Path, image_dir: Path, cams: dict) -> dict:
    posed = {v.name: v.w2c for v in read_colmap_scene(image_dir.parent, model, image_dir, fmt="photos").views}
    names = sorted(posed)
    return pose_errors(np.stack([posed[n] for n in names]), np.stack([cams[n][1] for n in names]))


# ----------------------------------------------------------------------------- pose errors
def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R_est, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1.0, -2.0, 0.5])
    with pytest.raises(ValueError):
        umeyama(src[:2], dst[:2])


def moved_world(w2cs: np.ndarray, S: np.ndarray) -> np.ndarray:
    """The same cameras [N, 4, 4] in a world moved by the similarity S [4, 4] (x -> S x)."""
    out = w2cs @ np.linalg.inv(S)
    out[:, :3, :] /= np.linalg.norm(out[:, 0, :3], axis=1)[:, None, None]  # rigid again: scale into t
    return out


def test_camera_similarity_recovers_a_similarity_and_uses_the_cameras_turn():
    ref = np.stack(ring_w2c(4, radius=3.0))
    S = np.eye(4)
    S[:3, :3] = 0.5 * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    S[:3, 3] = [1, 2, 3]
    s, R, t = camera_similarity(ref, moved_world(ref, S))
    assert s == pytest.approx(0.5) and np.allclose(s * R, S[:3, :3]) and np.allclose(t, S[:3, 3])
    # the centres lifted off their plane, one up and one down: Umeyama tilts the plane to follow
    # them; the cameras' own rotations keep it
    lifted = ref.copy()
    for i, dy in ((0, 0.3), (2, -0.3)):
        c = centers(ref)[i] + np.array([0, 0, dy])
        lifted[i, :3, 3] = -lifted[i, :3, :3] @ c
    tilt = lambda R: np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))  # noqa: E731
    assert tilt(camera_similarity(ref, lifted)[1]) < 1e-6
    assert tilt(umeyama(centers(ref), centers(lifted))[1]) > 3
    with pytest.raises(ValueError):
        camera_similarity(ref[:1], ref[:1])


def test_pose_errors_zero_for_a_moved_copy_and_see_a_turned_camera():
    ref = np.stack(ring_w2c(8, radius=3.0))
    S = np.eye(4)  # a world moved, turned and scaled: same cameras
    S[:3, :3] = 0.5 * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    S[:3, 3] = [1, 2, 3]
    est = moved_world(ref, S)
    err = pose_errors(est, ref)
    assert err["rotation_deg"].max() < 1e-6 and err["center"].max() < 1e-6
    turned = est.copy()
    c, s = np.cos(np.radians(5)), np.sin(np.radians(5))
    turned[0, :3, :] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ turned[0, :3, :]  # same centre
    err = pose_errors(turned, ref)
    assert err["rotation_deg"][0] == pytest.approx(5.0, abs=0.5) and np.median(err["rotation_deg"]) < 0.5


# ----------------------------------------------------------------------------- structure-from-motion
def test_sfm_recovers_the_rendered_cameras(photos, tmp_path):
    root, cams = photos
    image_dir, names, mask_dir = find_photos(root)
    res = pose_photos(image_dir, names, mask_dir, tmp_path / "model", "auto", 1600)
    assert res.registered == len(cams) == 20 and res.matcher == "exhaustive"
    err = estimated_vs_true(tmp_path / "model", image_dir, cams)
    # small photos of a small object leave the focal length loosely fixed: a real capture does
    # better (`python -m tools.bench sfm` on the instant-ngp fox: median 0.26 degrees, 0.5 %)
    assert np.median(err["rotation_deg"]) < 1.5 and err["rotation_deg"].max() < 4.0, err
    assert np.median(err["center"]) < 0.05, err
    assert not list(tmp_path.glob(".*tmp*")), "the staging folder is removed"


def test_sequential_matcher_poses_a_ring(photos, tmp_path):
    root, cams = photos
    image_dir, names, mask_dir = find_photos(root)
    res = pose_photos(image_dir, names, mask_dir, tmp_path / "model", "sequential", 1600)
    assert res.matcher == "sequential" and res.registered >= 18
    assert np.median(estimated_vs_true(tmp_path / "model", image_dir, cams)["rotation_deg"]) < 1.5


@pytest.mark.slow
def test_features_only_inside_the_masks(tmp_path):
    """A turntable: the room, the same in every photo, gives no 3D points."""
    cams = make_photos(tmp_path / "p", n=20, turntable=True)
    image_dir, names, mask_dir = find_photos(tmp_path / "p")
    pose_photos(image_dir, names, mask_dir, tmp_path / "model", "auto", 1600)
    rec = pycolmap.Reconstruction(str(tmp_path / "model"))
    assert rec.num_reg_images() >= 16
    outside = total = 0
    for im in rec.images.values():
        mask = read_image(mask_dir / im.name)[..., 0] > 0.5
        for p in im.points2D:
            if not p.has_point3D():  # (COLMAP keeps a few unmatched keypoints on the last image row)
                continue
            x, y = np.floor(p.xy).astype(int)
            total += 1
            near = mask[max(y - 6, 0) : y + 7, max(x - 6, 0) : x + 7]  # the mask is dilated for COLMAP
            outside += not near.any()
    assert total > 300 and outside == 0, (outside, total)
    assert len(cams) == 20
    # without the masks the room's features win: every other photo shows it, with SIFT as for the
    # 20 (auto would choose the learned matcher for 10)
    with pytest.raises(InputError, match="registered 0 of 10 photos.*masks"):
        pose_photos(image_dir, names[::2], None, tmp_path / "model2", "exhaustive", 1600)


@pytest.fixture(scope="module")
def prepared_photos(photos, tmp_path_factory):
    """`wgs prepare --views 4` on the 20 photos: (workspace, the command's run)."""
    base = tmp_path_factory.mktemp("prepared_photos")
    return base / "ws", run_wgs(["-w", base / "ws", "prepare", photos[0], "--views", "4"], base)


def test_prepare_poses_photos_once_then_reuses(photos, prepared_photos, tmp_path):
    root, _ = photos
    assert detect_format(root) == "photos"
    ws, proc = prepared_photos
    assert proc.returncode == 0, proc.stderr
    assert "20 of 20 photos registered" in proc.stderr
    info = json.loads((ws / "scene" / "scene.json").read_text())
    assert info["format"] == "photos" and len(info["train_names"]) == 4 and info["has_masks"]
    assert isinstance(info["resolution"][0], int), "one camera: every view undistorts to one size"
    assert pycolmap.Reconstruction(str(ws / "sfm")).num_cameras() == 1
    assert (ws / "sfm" / "cameras.bin").is_file()
    again = run_wgs(["-w", ws, "prepare", root, "--views", "4"], tmp_path)
    assert again.returncode == 0 and "already posed" in again.stderr and "up to date" in again.stderr


def test_flat_folder_of_photos_without_masks(tmp_path):
    make_photos(tmp_path / "flat", n=20, masks=False, layout="flat")
    image_dir, names, mask_dir = find_photos(tmp_path / "flat")
    assert image_dir == tmp_path / "flat" and mask_dir is None and len(names) == 20
    res = pose_photos(image_dir, names, None, tmp_path / "model", "auto", 1600)
    assert res.registered >= 18
    scene = read_scene(tmp_path / "flat", tmp_path / "model")
    assert scene.format == "photos" and len(scene.views) == res.registered


def test_four_photos_with_sift_say_how_to_pose_and_leave_the_workspace(tmp_path):
    make_photos(tmp_path / "four", n=4)
    ws = tmp_path / "ws"
    args = ["-w", ws, "prepare", tmp_path / "four", "--matcher", "exhaustive"]
    line = expect_error(tmp_path, args, "photos", "of 4 photos", "--views 4")
    assert "structure-from-motion needs many overlapping photos" in line
    assert not (ws / "sfm").exists() and not (ws / "scene").exists()
    assert not [p for p in ws.iterdir() if p.name != ".wgs.lock"] if ws.exists() else True


def test_unknown_matcher_is_refused(photos, tmp_path):
    root, _ = photos
    image_dir, names, mask_dir = find_photos(root)
    with pytest.raises(InputError, match="unknown matcher"):
        pose_photos(image_dir, names, mask_dir, tmp_path / "m", "vocab", 1600)
    proc = run_wgs(["-w", tmp_path / "ws", "prepare", root, "--matcher", "vocab"], tmp_path)
    assert proc.returncode == 2 and "vocab" in proc.stderr
    (tmp_path / "wgs.toml").write_text('[prepare]\nmatcher = "vocab"\n')
    expect_error(
        tmp_path, ["--config", tmp_path / "wgs.toml", "-w", tmp_path / "ws", "prepare", root], "matcher", "vocab"
    )


def test_a_photo_without_its_mask(tmp_path):
    make_photos(tmp_path / "p", n=12)
    (tmp_path / "p" / "masks" / "photo_005.png").unlink()
    expect_error(tmp_path, ["-w", tmp_path / "ws", "prepare", tmp_path / "p"], "masks", "photo_005.png", "no mask")


# ----------------------------------------------------------------------------- splits
def fake_scene(root: Path, n: int) -> RawScene:
    views = []
    for i, w2c in enumerate(ring_w2c(n, radius=3.0)):
        views.append(View(f"{i:03d}.png", root / f"{i:03d}.png", np.eye(3), w2c, 8, 8))
    return RawScene(root, "colmap", views)


def test_listed_test_views_are_never_chosen_for_training(tmp_path):
    """sparse_test.txt without sparse_N.txt: the N views come from the others (it used to fail
    with 'training and test views overlap')."""
    (tmp_path / "sparse_test.txt").write_text("0 4 8 12 16 20 24 28\n")
    scene = fake_scene(tmp_path, 32)
    choose_split(scene, 8, 8)
    assert len(scene.train) == 8 and not set(scene.train) & set(scene.test)
    assert sorted(scene.test) == [0, 4, 8, 12, 16, 20, 24, 28]


# ----------------------------------------------------------------------------- LLFF
def to_llff_pose(w2c: np.ndarray, h: int, w: int, f: float) -> np.ndarray:
    """Our world-to-camera -> LLFF's 3x5 [down, right, back, centre, hwf] (the inverse of the reader)."""
    c2w = np.linalg.inv(w2c)
    right, down, fwd, center = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
    return np.stack([down, right, -fwd, center, [h, w, f]], axis=1)


def make_llff(
    root: Path,
    n: int = 6,
    h: int = 24,
    w: int = 32,
    f: float = 30.0,
    folder: str = "images",
    scale: int = 1,
    masks: bool = False,
) -> list[np.ndarray]:
    root.mkdir(parents=True, exist_ok=True)
    w2cs = ring_w2c(n, radius=3.0, height=0.4)
    rows = [np.concatenate([to_llff_pose(m, h, w, f).reshape(-1), [0.5, 6.0]]) for m in w2cs]
    np.save(root / "poses_bounds.npy", np.stack(rows))
    for i in range(n):
        write_png(root / folder / f"img_{i:02d}.png", np.full((h // scale, w // scale, 3), i / n, np.float32))
        if masks:
            write_png(root / "masks" / f"img_{i:02d}.png", np.ones((h // scale, w // scale), np.float32))
    return w2cs


def test_llff_pose_convention_round_trip():
    w2c = ring_w2c(1, radius=2.0, height=0.5)[0]
    assert np.allclose(llff_to_w2c(to_llff_pose(w2c, 10, 10, 10)[:, :4]), w2c)


def test_llff_reader(tmp_path):
    w2cs = make_llff(tmp_path, masks=True)
    scene = read_scene(tmp_path)
    assert scene.format == "llff" and len(scene.views) == 6
    for v, ref in zip(scene.views, w2cs, strict=True):
        assert np.allclose(v.w2c, ref, atol=1e-9)
        assert np.allclose(v.K, [[30, 0, 16], [0, 30, 12], [0, 0, 1]]) and v.mask is not None


def test_llff_images_k_only_scales_the_focal_length(tmp_path):
    make_llff(tmp_path, folder="images_4", scale=4, h=96, w=128, f=120.0)
    v = read_scene(tmp_path).views[0]
    assert (v.width, v.height) == (32, 24) and np.allclose(np.diag(v.K)[:2], [30.0, 30.0])


def test_llff_prepare_end_to_end(tmp_path):
    make_llff(tmp_path / "s", n=8)
    proc = run_wgs(["-w", tmp_path / "ws", "prepare", tmp_path / "s", "--views", "3"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "ws" / "scene" / "scene.json").read_text())["format"] == "llff"


@pytest.mark.parametrize(
    "bad, needle", [("shape", "[N, 17]"), ("count", "poses for"), ("nan", "NaN"), ("focal", "non-positive")]
)
def test_llff_bad_poses(tmp_path, bad, needle):
    make_llff(tmp_path / "s")
    arr = np.load(tmp_path / "s" / "poses_bounds.npy")
    arr = {
        "shape": arr[:, :15],
        "count": arr[:5],
        "nan": np.where(np.arange(17) == 3, np.nan, arr),
        "focal": np.concatenate([arr[:, :14], -arr[:, 14:15], arr[:, 15:]], 1),
    }[bad]
    np.save(tmp_path / "s" / "poses_bounds.npy", arr)
    expect_error(tmp_path, ["-w", tmp_path / "ws", "prepare", tmp_path / "s"], "poses_bounds.npy", needle)


def test_eval_localises_the_test_cameras_of_photos_it_posed(photos, prepared_photos, tmp_path):
    """Test photos posed with the training photos carry the pose error of structure-from-motion:
    eval moves each camera to where the final model fits it best, scores there and says so."""
    from conftest import TINY

    root, _ = photos
    (tmp_path / "wgs.toml").write_text(TINY + "localise_steps = 5\n")
    ws = tmp_path / "ws"
    shutil.copytree(prepared_photos[0] / "sfm", ws / "sfm")  # the same photos and settings: posed once
    proc = run_wgs(
        ["--config", tmp_path / "wgs.toml", "-w", ws, "all", root, "--views", "4", "--downscale", "4"],
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    res = json.loads((ws / "6_eval" / "results.json").read_text())
    moved = res["test_cameras_localised"]
    assert moved["steps"] == 5 and moved["median_rotation_deg"] > 0 and res["views"] == "test"
    cams = json.loads((ws / "6_eval" / "test_cameras.json").read_text())
    assert set(cams["rotation_deg"]) == set(json.loads((ws / "6_eval" / "per_view.json").read_text())["psnr"])
    assert "photos already posed, reused" in proc.stderr
    assert "test cameras localised on the fine model (5 steps each)" in proc.stderr
    assert "their cameras localised on the model" in proc.stdout + proc.stderr
