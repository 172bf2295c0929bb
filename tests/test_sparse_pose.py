"""Four photos without cameras: learned matching poses them (`wgs.scene.sfm`, matcher "learned"),
or one error line names the photos that share too little. Photos rendered by our own renderer
(tests/photo_scene.py, 320x240, masks)."""

import json
import shutil
import socket

import numpy as np
import pytest
from conftest import expect_error
from photo_scene import as_exif_jpegs, make_photos

from wgs import progress
from wgs.fields import facts
from wgs.io.images import read_image, write_png
from wgs.scene.colmap import read_colmap_scene
from wgs.scene.native_colmap import pycolmap
from wgs.scene.pose_error import pose_errors
from wgs.scene.sfm import MATCHERS, find_photos, pose_photos
from wgs.stages.prepare.settings import PrepareConfig

# learned features at a long side of 768 px: the default (1024) enlarges these 320x240 photos
# further and takes twice the time (`prepare.match_side`)
SIDE = 768
SMALL = f"[prepare]\nmatch_side = {SIDE}\n"


def test_matcher_choices_are_the_config_fields():
    assert MATCHERS == facts(PrepareConfig, "matcher")["choices"]


@pytest.mark.slow
def test_four_photos_45_degrees_apart_are_posed_offline(tmp_path, monkeypatch):
    """All 4 posed, median rotation <= 2 degrees and centre <= 5 % of the camera extent after a
    similarity alignment, with every network connection refused."""
    cams = make_photos(tmp_path / "p", n=4, azimuths=[0, 45, 90, 135])

    def no_network(*_args, **_kw):
        raise AssertionError("posing reached for the network")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(socket, "create_connection", no_network)
    image_dir, names, mask_dir = find_photos(tmp_path / "p")
    res = pose_photos(image_dir, names, mask_dir, tmp_path / "model", "auto", 1600, match_side=SIDE)
    assert res.matcher == "learned" and res.registered == 4
    posed = {
        v.name: v.w2c for v in read_colmap_scene(tmp_path / "p", tmp_path / "model", image_dir, fmt="photos").views
    }
    keys = sorted(posed)
    err = pose_errors(np.stack([posed[k] for k in keys]), np.stack([cams[k][1] for k in keys]))
    assert np.median(err["rotation_deg"]) <= 2.0 and np.median(err["center"]) <= 0.05, err
    # the points only two photos see are triangulated too (`sfm.SPARSE_TWO_VIEW_TRACKS`): most of
    # what photos 45 degrees apart share
    tracks = [len(p.track.elements) for p in pycolmap.Reconstruction(str(tmp_path / "model")).points3D.values()]
    assert sum(n == 2 for n in tracks) > sum(n > 2 for n in tracks), np.bincount(tracks)


@pytest.mark.slow
def test_the_focal_length_the_photos_exif_gives_is_held(tmp_path, capsys, monkeypatch):
    """4 JPEGs 30 degrees apart whose EXIF gives their focal length (35 mm equivalent, whole mm),
    with `hold_exif_focal`: posed with that focal, unrefined, and within the posing tolerance."""
    cams = make_photos(tmp_path / "p", n=4, azimuths=[0, 30, 60, 90])
    exif = as_exif_jpegs(tmp_path / "p", float(cams["photo_000.png"][0][0, 0]))
    image_dir, names, mask_dir = find_photos(tmp_path / "p")
    monkeypatch.setattr(progress, "_quiet", False)
    monkeypatch.setattr(progress.console, "quiet", False)
    res = pose_photos(
        image_dir, names, mask_dir, tmp_path / "model", "auto", 1600, match_side=SIDE, hold_exif_focal=True
    )
    assert f"the focal length from the photos' EXIF ({exif:.0f} px" in " ".join(capsys.readouterr().err.split())
    assert res.registered == 4
    views = read_colmap_scene(tmp_path / "p", tmp_path / "model", image_dir, fmt="photos").views
    focals = [float(v.K[0, 0]) for v in views]
    assert focals == pytest.approx([exif] * 4, rel=1e-9), focals
    err = pose_errors(np.stack([v.w2c for v in views]), np.stack([cams[v.name[:-4] + ".png"][1] for v in views]))
    assert np.median(err["rotation_deg"]) <= 2.0 and np.median(err["center"]) <= 0.05, err


@pytest.mark.slow
def test_a_photo_stored_turned_is_matched_turned_and_posed(tmp_path, capsys, monkeypatch):
    """A phone held the other way stores its photo turned (EXIF orientation, which wgs does not
    apply): photo_001 turned clockwise by 90 degrees matches nothing as it is; matched turned back,
    all 4 pose, the turned one as a camera rolled by 90 degrees."""
    cams = make_photos(tmp_path / "p", n=4, width=256, height=256, azimuths=[0, 30, 60, 90])
    for sub in ("images", "masks"):
        path = tmp_path / "p" / sub / "photo_001.png"
        write_png(path, np.ascontiguousarray(np.rot90(read_image(path), -1)))
    roll = np.eye(4)
    roll[:2, :2] = [[0, -1], [1, 0]]  # camera (X, Y, Z) -> (-Y, X, Z): the image turned clockwise
    truth = {k: (roll @ w2c if k == "photo_001.png" else w2c) for k, (_, w2c) in cams.items()}
    image_dir, names, mask_dir = find_photos(tmp_path / "p")
    monkeypatch.setattr(progress, "_quiet", False)  # an earlier `wgs -q` in this worker set it
    monkeypatch.setattr(progress.console, "quiet", False)
    res = pose_photos(image_dir, names, mask_dir, tmp_path / "model", "auto", 1600, match_side=SIDE)
    assert "photo_001.png matches the others turned by 90 degrees" in " ".join(capsys.readouterr().err.split())
    assert res.registered == 4
    posed = {
        v.name: v.w2c for v in read_colmap_scene(tmp_path / "p", tmp_path / "model", image_dir, fmt="photos").views
    }
    keys = sorted(posed)
    err = pose_errors(np.stack([posed[k] for k in keys]), np.stack([truth[k] for k in keys]))
    assert np.median(err["rotation_deg"]) <= 2.0 and np.median(err["center"]) <= 0.05, err


@pytest.mark.slow
def test_two_objects_are_refused_naming_the_photos(tmp_path):
    """Two photos each of two different objects: no 3 pose together; nothing is written."""
    make_photos(tmp_path / "a", n=2, azimuths=[0, 20], seed=0)
    make_photos(tmp_path / "b", n=2, azimuths=[0, 20], seed=5, shape_seed=7)
    scene = tmp_path / "scene"
    for src, tag in ((tmp_path / "a", "a"), (tmp_path / "b", "b")):
        for sub in ("images", "masks"):
            for p in (src / sub).iterdir():
                (scene / sub).mkdir(parents=True, exist_ok=True)
                p.rename(scene / sub / f"{tag}_{p.name}")
    ws = tmp_path / "ws"
    (tmp_path / "small.toml").write_text(SMALL)
    line = expect_error(
        tmp_path,
        ["--config", tmp_path / "small.toml", "-w", ws, "prepare", scene],
        "pose together",
        "share too little",
        "a_photo_000.png",
    )
    assert "b_photo_000.png" in line
    assert not (ws / "sfm").exists() and not (ws / "scene").exists()


@pytest.mark.slow
def test_three_that_pose_are_kept_and_the_fourth_is_named(tmp_path):
    """Three photos 30 degrees apart pose; one 140 degrees from them is left out with one line, and
    the scene trains on the three (the masks agree with their poses)."""
    from conftest import run_wgs

    make_photos(tmp_path / "p", n=4, azimuths=[0, 30, 60, 200])
    (tmp_path / "short.toml").write_text(SMALL + 'camera_iterations = 40\nmirror = "none"\n')
    proc = run_wgs(["--config", tmp_path / "short.toml", "-w", tmp_path / "ws", "prepare", tmp_path / "p"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    err = " ".join(proc.stderr.split())
    assert "photo_003.png left out: it shares too little" in err and "3 of 4 photos registered" in err
    # photos wgs posed from a few views: their cameras are corrected, or kept as posed, in one line
    record = json.loads((tmp_path / "ws" / "scene" / "scene.json").read_text())["cameras_corrected"]
    said = "cameras: corrected by training" if record["kept"] else "cameras: kept as posed"
    assert said in err and "of a photo's mask" in err, err
    assert "nothing checks the poses" not in err  # the masks checked them
    assert json.loads((tmp_path / "ws" / "scene" / "scene.json").read_text())["train_names"] == [
        f"photo_00{i}.png" for i in range(3)
    ]


@pytest.mark.slow
def test_photos_170_degrees_apart_are_refused_naming_them(tmp_path):
    """A close pair and a photo 150-170 degrees from it: the far photo's matches with the pair
    (45-60 of them pass two-view verification, on like-looking parts) once placed it 55 degrees
    from the pair, against 150-170 in truth. LightGlue is sure of too few of them: it is refused."""
    make_photos(tmp_path / "p", n=3, azimuths=[0, 20, 170])
    (tmp_path / "small.toml").write_text(SMALL)
    line = expect_error(
        tmp_path,
        ["--config", tmp_path / "small.toml", "-w", tmp_path / "ws", "prepare", tmp_path / "p"],
        "pose together",
        "photo_002.png",
    )
    assert "one more photo between photo_001.png and photo_002.png" in line
    assert not (tmp_path / "ws" / "scene").exists()


def test_poses_that_disagree_with_the_masks_are_refused(finished_workspace, tmp_path):
    """The check after learned posing: the tiny scene's own poses pass; one training photo's camera
    moved sideways makes the other photos' hull leave out much of its mask: one error naming it."""
    from wgs.errors import InputError
    from wgs.scene.dataset import load_prepared
    from wgs.stages.prepare.run import poses_agree_with_masks

    scene = tmp_path / "scene"
    shutil.copytree(finished_workspace[0] / "ws" / "scene", scene)
    poses_agree_with_masks(scene, tmp_path)
    moved = load_prepared(scene).photos[1].name
    images = [line.split() for line in (scene / "sparse" / "images.txt").read_text().splitlines()]
    image_id = next(f[0] for f in images if len(f) == 10 and f[9] == moved)
    frames = (scene / "sparse" / "frames.txt").read_text().splitlines()
    for i, line in enumerate(frames):  # FRAME_ID RIG_ID QW QX QY QZ TX TY TZ 1 CAMERA SENSOR_ID DATA_ID
        fields = line.split()
        if not line.startswith("#") and fields[-1] == image_id:
            fields[6] = str(float(fields[6]) + 0.2)  # the camera moved sideways by 0.2 of the object's extent
            frames[i] = " ".join(fields)
    (scene / "sparse" / "frames.txt").write_text("\n".join(frames) + "\n")
    with pytest.raises(InputError, match=f"disagree with the masks.*{moved}"):
        poses_agree_with_masks(scene, tmp_path)


def test_fewer_than_three_photos_are_refused_at_once(tmp_path):
    make_photos(tmp_path / "p", n=2, azimuths=[0, 20])
    expect_error(tmp_path, ["-w", tmp_path / "ws", "prepare", tmp_path / "p"], "2 photos", "at least 3")


def test_a_pair_verifies_the_same_alone_and_among_others(tmp_path):
    """COLMAP's RANSAC is seeded (`sfm.verification_options`): a pair's verified matches do not hang
    on which pairs a thread verified before it, so the same photos pose the same every run. Four
    views of 400 points, 2 px of noise, half of each pair's matches wrong."""
    import itertools

    import pycolmap

    from wgs.io.images import write_png
    from wgs.scene.sfm import verification_options

    rng = np.random.default_rng(0)
    names = [f"p{i}.png" for i in range(4)]
    for name in names:
        write_png(tmp_path / "images" / name, np.zeros((240, 320, 3), np.float32))
    db = tmp_path / "matches.db"
    pycolmap.Database.open(db).close()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model, reader.camera_params = "PINHOLE", "300,300,160,120"
    pycolmap.import_images(db, tmp_path / "images", pycolmap.CameraMode.SINGLE, options=reader)
    points = rng.normal(size=(400, 3)) * 0.5
    database = pycolmap.Database.open(db)
    ids = {im.name: im.image_id for im in database.read_all_images()}
    for i, name in enumerate(names):
        a = 0.4 * i  # turned about the vertical axis, 4 units from the points
        cam = points @ np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]).T + [0, 0, 4]
        px = 300 * cam[:, :2] / cam[:, 2:] + [160, 120] + rng.normal(size=(400, 2)) * 2
        database.write_keypoints(ids[name], px.astype(np.float32))
    pairs = list(itertools.combinations(names, 2))
    for a, b in pairs:
        wrong = rng.random(400) < 0.5
        matches = np.stack([np.arange(400), np.where(wrong, rng.integers(0, 400, 400), np.arange(400))], 1)
        database.write_matches(ids[a], ids[b], matches.astype(np.uint32))
    database.close()

    def verified(which: list[tuple[str, str]], run: int) -> bytes:
        copy, pair_file = tmp_path / f"run{run}.db", tmp_path / f"pairs{run}.txt"
        shutil.copy(db, copy)
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in which))
        pycolmap.verify_matches(copy, pair_file, options=verification_options(sparse=True))
        database = pycolmap.Database.open(copy)
        try:
            inliers = database.read_two_view_geometry(ids[pairs[-1][0]], ids[pairs[-1][1]]).inlier_matches
        finally:
            database.close()
        assert len(inliers) > 150
        return inliers.tobytes()

    runs = [verified(which, k) for k, which in enumerate((pairs, pairs[-1:], pairs, pairs[-1:]))]
    assert len(set(runs)) == 1


def test_poses_without_masks_of_the_users_are_said_to_be_unchecked():
    """Automatic masks are made under the poses and agree with wrong ones: posed photos without
    masks of the user's get one line that says nothing checks them and how masks would; the
    user's masks (given, or a --masks folder) are checked against the hull instead."""
    from wgs.stages.prepare.run import unchecked_poses_line

    for source in ("auto", "none"):
        line = unchecked_poses_line(4, source)
        assert line is not None and line.startswith("cameras: posed by wgs from 4 photos without masks")
        assert "nothing checks the poses" in line and "--masks DIR" in line
    assert unchecked_poses_line(4, "given") is None and unchecked_poses_line(4, "folder") is None
