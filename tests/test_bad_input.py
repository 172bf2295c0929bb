"""Bad input: one line naming the file and the problem, exit status 2, no traceback."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import expect_error, run_cli

from wgs.io.images import write_png


def prep(scene, tmp_path, *extra):
    return ["-w", str(tmp_path / "ws"), "prepare", str(scene), *extra]


def frames(scene: Path, split="train"):
    return json.loads((scene / f"transforms_{split}.json").read_text())


def save(scene: Path, data, split="train"):
    (scene / f"transforms_{split}.json").write_text(json.dumps(data))


def test_missing_folder(tmp_path):
    expect_error(tmp_path, prep(tmp_path / "nope", tmp_path), "nope", "not found")


def test_unknown_format_lists_what_was_found(tmp_path):
    d = tmp_path / "weird"
    (d / "pictures").mkdir(parents=True)
    (d / "notes.txt").write_text("hi")
    expect_error(tmp_path, prep(d, tmp_path), "no known scene format", "pictures/", "notes.txt")


def test_garbage_image(scene_copy, tmp_path):
    (scene_copy / "train" / "r_1.png").write_bytes(b"\x89PNG not really")
    expect_error(tmp_path, prep(scene_copy, tmp_path), "r_1.png", "cannot read image")


def test_truncated_image(scene_copy, tmp_path):
    p = scene_copy / "train" / "r_2.png"
    p.write_bytes(p.read_bytes()[:200])
    expect_error(tmp_path, prep(scene_copy, tmp_path), "r_2.png")


def test_image_truncated_inside_its_pixels_gives_one_line(scene_copy, tmp_path):
    """The decoder's own messages (libpng prints to stderr) are silenced: stderr is our one line."""
    p = scene_copy / "train" / "r_2.png"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    proc = run_cli(prep(scene_copy, tmp_path), tmp_path)
    assert proc.returncode == 2
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "r_2.png" in errors[0] and "truncated" in errors[0], proc.stderr
    assert "libpng" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


def test_images_of_different_sizes(scene_copy, tmp_path):
    write_png(scene_copy / "train" / "r_3.png", np.ones((40, 48, 4), np.float32))
    expect_error(tmp_path, prep(scene_copy, tmp_path), "r_3.png", "48x40")


@pytest.mark.parametrize("bad,needle", [(float("nan"), "NaN"), (0.0, "singular")])
def test_bad_pose(scene_copy, tmp_path, bad, needle):
    data = frames(scene_copy)
    m = np.asarray(data["frames"][1]["transform_matrix"])
    if needle == "NaN":
        m[0, 0] = bad
    else:
        m[:3, 0] = 0.0
    data["frames"][1]["transform_matrix"] = m.tolist()
    (scene_copy / "transforms_train.json").write_text(json.dumps(data).replace("NaN", "NaN"))
    expect_error(tmp_path, prep(scene_copy, tmp_path), "transforms_train.json", "frame 1", needle)


def test_scaled_pose_is_not_a_rotation(scene_copy, tmp_path):
    data = frames(scene_copy)
    m = np.asarray(data["frames"][0]["transform_matrix"])
    m[:3, :3] *= 2.0
    data["frames"][0]["transform_matrix"] = m.tolist()
    save(scene_copy, data)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "not a rotation")


def test_zero_fov(scene_copy, tmp_path):
    data = frames(scene_copy)
    data["camera_angle_x"] = 0.0
    save(scene_copy, data)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "transforms_train.json", "camera_angle_x")


def test_zero_focal_length_ngp(scene_formats, tmp_path):
    import shutil

    d = tmp_path / "ngp"
    shutil.copytree(scene_formats["ngp"], d)
    meta = json.loads((d / "transforms.json").read_text())
    meta["fl_x"] = 0.0
    (d / "transforms.json").write_text(json.dumps(meta))
    expect_error(tmp_path, prep(d, tmp_path), "transforms.json", "focal length")


def test_empty_mask(scene_copy, tmp_path):
    img = np.zeros((48, 48, 4), np.float32)  # fully transparent: the object is nowhere
    write_png(scene_copy / "train" / "r_0.png", img)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "r_0.png", "mask is empty")


def test_all_white_mask(scene_formats, tmp_path):
    import shutil

    d = tmp_path / "ngp"
    shutil.copytree(scene_formats["ngp"], d)
    name = sorted((d / "masks").iterdir())[0]
    write_png(name, np.ones((48, 48), np.float32))
    expect_error(tmp_path, prep(d, tmp_path), name.name, "all foreground")


def test_mask_size_differs(scene_formats, tmp_path):
    import shutil

    d = tmp_path / "ngp"
    shutil.copytree(scene_formats["ngp"], d)
    name = sorted((d / "masks").iterdir())[0]
    write_png(name, np.ones((24, 24), np.float32))
    expect_error(tmp_path, prep(d, tmp_path), name.name, "24x24")


def test_split_id_out_of_range(scene_formats, tmp_path):
    import shutil

    d = tmp_path / "colmap"
    shutil.copytree(scene_formats["colmap"], d)
    (d / "sparse_3.txt").write_text("0 1 99\n")
    expect_error(tmp_path, prep(d, tmp_path, "--views", "3"), "sparse_3.txt", "99", "out of range")


def test_split_overlap(scene_formats, tmp_path):
    import shutil

    d = tmp_path / "colmap"
    shutil.copytree(scene_formats["colmap"], d)
    (d / "sparse_3.txt").write_text("0 1 2\n")
    (d / "sparse_test.txt").write_text("2 3 4\n")
    expect_error(tmp_path, prep(d, tmp_path, "--views", "3"), "sparse_test.txt", "overlap")


def test_fewer_than_two_views(scene_copy, tmp_path):
    data = frames(scene_copy)
    data["frames"] = data["frames"][:1]
    save(scene_copy, data)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "at least 2 training views")
    expect_error(tmp_path, prep(scene_copy, tmp_path, "--views", "1"), "--views")


@pytest.mark.parametrize("path", ["../../etc/passwd", "/etc/passwd"])
def test_file_path_outside_scene_refused(scene_copy, tmp_path, path):
    data = frames(scene_copy)
    data["frames"][0]["file_path"] = path
    save(scene_copy, data)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "transforms_train.json", "refus")


def test_symlink_outside_scene_refused(scene_copy, tmp_path):
    outside = tmp_path / "outside.png"
    write_png(outside, np.ones((48, 48, 4), np.float32))
    (scene_copy / "train" / "r_0.png").unlink()
    (scene_copy / "train" / "r_0.png").symlink_to(outside)
    expect_error(tmp_path, prep(scene_copy, tmp_path), "outside the scene folder")


def test_invalid_json(scene_copy, tmp_path):
    (scene_copy / "transforms_train.json").write_text("{not json")
    expect_error(tmp_path, prep(scene_copy, tmp_path), "transforms_train.json", "not valid JSON")


def test_huge_image_refused(scene_copy, tmp_path):
    expect_error(tmp_path, prep(scene_copy, tmp_path, "--max-pixels", "100"), "r_0.png", "--max-pixels")


@pytest.mark.parametrize(
    "toml,needle",
    [
        ("[coarse]\niterationz = 5\n", "coarse.iterationz"),
        ("[coarse]\niterations = 'many'\n", "coarse.iterations"),
        ("[nosuchstage]\nx = 1\n", "nosuchstage"),
        ("seed = 'x'\n", "seed"),
        ("[coarse\n", "not valid TOML"),
    ],
)
def test_bad_config(scene_copy, tmp_path, toml, needle):
    cfg = tmp_path / "wgs.toml"
    cfg.write_text(toml)
    expect_error(tmp_path, ["--config", str(cfg), *prep(scene_copy, tmp_path)], "wgs.toml", needle)


def test_failed_prepare_keeps_previous_workspace(scene_copy, tmp_path):
    ok = run_cli(prep(scene_copy, tmp_path), tmp_path)
    assert ok.returncode == 0, ok.stderr
    manifest = (tmp_path / "ws" / "scene" / "manifest.json").read_text()
    run_record = (tmp_path / "ws" / "run.json").read_text()  # the estimate printed after it
    (scene_copy / "train" / "r_1.png").write_bytes(b"broken")
    expect_error(tmp_path, prep(scene_copy, tmp_path), "r_1.png")
    assert (tmp_path / "ws" / "scene" / "manifest.json").read_text() == manifest
    assert (tmp_path / "ws" / "run.json").read_text() == run_record
    assert sorted(p.name for p in (tmp_path / "ws").iterdir()) == ["run.json", "scene"]


def test_info_without_workspace(tmp_path):
    expect_error(tmp_path, ["info"], "workspace")


def test_all_in_an_empty_folder_without_workspace(tmp_path):
    """`wgs all .` names its workspace beside the folder, then says the folder holds no scene."""
    empty = tmp_path / "photos"
    empty.mkdir()
    expect_error(empty, ["all", "."], "photos")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no workspace left behind


def test_global_option_after_the_command_says_where_it_goes(tmp_path):
    proc = run_cli(["all", "scene", "--device", "cpu"], tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "--device is a global option: put it before the command" in proc.stderr
