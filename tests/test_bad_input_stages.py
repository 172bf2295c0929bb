"""Bad input inside a workspace and at the scene's edge: damaged stage files, foreign checkpoints,
another scene, an empty visual hull, odd file names. Each: exit 2, one `error:` line naming the file,
no traceback, and nothing a later stage could take for a result.
"""

import io
import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import expect_error, make_scene, run_wgs, to_idr

from wgs.config import as_dict, load_config_file
from wgs.context import RunOptions
from wgs.io.images import read_image, write_png
from wgs.workspace import Workspace


@pytest.fixture(scope="module")
def done(finished_workspace):
    """The session's finished tiny `wgs all` workspace (copied by each test)."""
    return finished_workspace[0]


@pytest.fixture
def ws(done, tmp_path):
    """A copy of the finished workspace, with the tiny config beside it."""
    shutil.copytree(done / "ws", tmp_path / "ws")
    shutil.copy(done / "wgs.toml", tmp_path / "wgs.toml")
    return tmp_path / "ws"


def wgs(ws: Path, *args, resume: bool = False):
    """CLI arguments for the copied workspace, with the tiny config beside it."""
    return ["-q", "--config", ws.parent / "wgs.toml", *(["--resume"] if resume else []), "-w", ws, *args]


def first(ws: Path, pattern: str) -> Path:
    return sorted(ws.glob(pattern))[0]


def unchanged(ws: Path, stage_dir: str, before: str) -> None:
    """The failed stage left its last good output (its manifest) as it was."""
    assert (ws / stage_dir / "manifest.json").read_text() == before


def test_truncated_exr_pair(ws):
    exr = first(ws, "2_mask_data/pairs/ll/*.exr")
    exr.write_bytes(exr.read_bytes()[:200])
    before = (ws / "3_finetune/manifest.json").read_text()
    expect_error(ws.parent, wgs(ws, "finetune", "--force"), exr.name)
    unchanged(ws, "3_finetune", before)


def test_exr_that_is_not_an_exr(ws):
    exr = first(ws, "1_coarse/subbands/render/*.exr")
    exr.write_text("this is not an image")
    expect_error(ws.parent, wgs(ws, "finetune", "--force"), exr.name)


def test_truncated_checkpoint(ws):
    ck = ws / "1_coarse/ckpt.pt"
    ck.write_bytes(ck.read_bytes()[: ck.stat().st_size // 2])
    expect_error(
        ws.parent, wgs(ws, "render", "--stage", "coarse", "--views", "test"), "ckpt.pt", "not a valid wgs checkpoint"
    )


def resave(ck: Path, edit) -> None:
    blob = torch.load(ck, weights_only=True)
    edit(blob)
    torch.save(blob, ck)


def test_checkpoint_from_an_incompatible_version(ws):
    resave(ws / "1_coarse/ckpt.pt", lambda b: b.update(version=999))
    expect_error(ws.parent, wgs(ws, "repair", "--force"), "ckpt.pt", "version 999")


def test_checkpoint_with_an_sh_degree_that_does_not_fit(ws):
    def edit(b):
        n = b["splats"]["means"].shape[0]
        b["splats"]["shN"] = torch.zeros(n, 5, 3)  # 1 + 5 coefficients: no SH degree has 6

    resave(ws / "5_fine/ckpt.pt", edit)
    expect_error(ws.parent, wgs(ws, "eval", "--force"), "ckpt.pt", "not an SH degree")


class Payload:
    def __reduce__(self):
        return (os.system, ("touch PWNED",))


def test_checkpoint_with_a_pickle_payload_is_refused_and_not_run(ws):
    ck = ws / "1_coarse/ckpt.pt"
    ck.write_bytes(pickle.dumps({"version": 1, "splats": Payload()}))
    expect_error(ws.parent, wgs(ws, "render", "--stage", "coarse", "--views", "test"), "ckpt.pt")
    assert not (ws.parent / "PWNED").exists()


def test_corrupt_model_weights(ws):
    w = ws / "3_finetune/D/model.safetensors"
    w.write_bytes(b"\x00" * 64)
    expect_error(ws.parent, wgs(ws, "repair", "--force"), "model.safetensors")
    assert not any(p.name.startswith(".4_repair") for p in ws.iterdir())


def test_model_config_of_another_shape(ws):
    c = ws / "3_finetune/D/config.json"
    cfg = json.loads(c.read_text())
    cfg["channels"] = "wide"
    c.write_text(json.dumps(cfg))
    expect_error(ws.parent, wgs(ws, "repair", "--force"), "config.json")


def test_workspace_of_another_scene(ws, tmp_path):
    other = make_scene(tmp_path / "other", seed=5, size=48, n_train=4, n_test=3)
    before = (ws / "scene/manifest.json").read_text()
    expect_error(ws.parent, wgs(ws, "all", other), "holds another scene", "--force")
    unchanged(ws, "scene", before)
    assert (ws / "6_eval/results.json").exists()


def test_views_that_share_no_object_region(tmp_path, blender_scene):
    """Masks in disjoint corners: the visual hull is empty; say so and what to check."""
    scene = tmp_path / "scene"
    shutil.copytree(blender_scene, scene)
    train = sorted((scene / "train").glob("*.png"))
    for k, p in enumerate(train):
        img = read_image(p)
        h, w = img.shape[:2]
        img[..., 3] = 0.0
        q = h // 4  # each view's object in another corner
        img[[slice(0, q), slice(h - q, h)][k // 2 % 2], [slice(0, q), slice(w - q, w)][k % 2], 3] = 1.0
        write_png(p, img)
    expect_error(tmp_path, ["-q", "-w", tmp_path / "ws", "coarse"], "prepare stage has not run", "wgs prepare")
    assert run_wgs(["-q", "-w", tmp_path / "ws", "prepare", scene], tmp_path).returncode == 0
    expect_error(tmp_path, ["-q", "-w", tmp_path / "ws", "coarse"], str(scene), "visual hull", "empty", "masks")
    assert not (tmp_path / "ws" / "1_coarse").exists()


def test_non_utf8_file_name(tmp_path, blender_scene):
    idr = to_idr(blender_scene, tmp_path / "idr")
    img = sorted((idr / "image").iterdir())[0]
    os.rename(img, os.path.join(os.fsencode(img.parent), b"caf\xe9.png"))
    expect_error(tmp_path, ["-q", "-w", tmp_path / "ws", "prepare", idr], "UTF-8")


def test_idr_cameras_file_holding_a_single_array(tmp_path, blender_scene):
    idr = to_idr(blender_scene, tmp_path / "idr")
    buf = io.BytesIO()
    np.save(buf, np.eye(4))
    (idr / "cameras_sphere.npz").write_bytes(buf.getvalue())
    expect_error(tmp_path, ["-q", "-w", tmp_path / "ws", "prepare", idr], "cameras_sphere.npz", "single array")


def test_frame_that_is_not_an_object(tmp_path, blender_scene):
    scene = tmp_path / "scene"
    shutil.copytree(blender_scene, scene)
    meta = json.loads((scene / "transforms_train.json").read_text())
    meta["frames"][1] = "r_1.png"
    (scene / "transforms_train.json").write_text(json.dumps(meta))
    expect_error(
        tmp_path, ["-q", "-w", tmp_path / "ws", "prepare", scene], "transforms_train.json", "frame 1 is not an object"
    )


def test_damaged_resume_state(ws):
    """--resume with a damaged saved state: one line naming it, a hint to start over."""
    shutil.rmtree(ws / "5_fine")
    rdir = ws / ".resume" / "5_fine"
    (rdir / "out").mkdir(parents=True)
    (rdir / "gf.pt").write_bytes(b"PK\x03\x04 damaged")
    ctx = RunOptions(ws, "cpu", 0, False, load_config_file(ws.parent / "wgs.toml"))
    fp = Workspace(ws).stage_fingerprint("fine", as_dict(ctx.config("fine", None)), {"seed": 0})
    (rdir / "fingerprint").write_text(fp)  # the saved state belongs to this very run
    expect_error(ws.parent, wgs(ws, "fine", resume=True), "gf.pt", "without --resume")


@pytest.mark.parametrize(
    "name,needle", [(b"../../outside.png", b"points outside the scene folder"), (b"caf\xe9.png", b"not valid UTF-8")]
)
def test_colmap_image_name_escaping_or_not_utf8(tmp_path, blender_scene, name, needle):
    from conftest import to_colmap

    scene = to_colmap(blender_scene, tmp_path / "colmap")
    images_txt = scene / "sparse" / "0" / "images.txt"
    data = images_txt.read_bytes()
    first = sorted(p.name for p in (scene / "images").iterdir())[0].encode()
    images_txt.write_bytes(data.replace(b" " + first + b"\n", b" " + name + b"\n", 1))
    expect_error(tmp_path, ["-q", "-w", tmp_path / "ws", "prepare", scene], needle.decode(), "sparse")


@pytest.mark.parametrize("damage", ["truncated", "missing"])
def test_damaged_or_missing_prior_weights(ws, tmp_path, damage):
    from wgs.weights import WEIGHTS

    prior = tmp_path / "prior"
    shutil.copytree(WEIGHTS, prior)
    w = prior / "D" / "model.safetensors"
    if damage == "truncated":
        w.write_bytes(w.read_bytes()[:100])
    else:
        w.unlink()
    before = (ws / "3_finetune/manifest.json").read_text()
    expect_error(ws.parent, wgs(ws, "finetune", "--force", "--prior", prior), "model.safetensors")
    unchanged(ws, "3_finetune", before)


def test_wgs_reads_no_file_with_pickle_code():
    """Every torch.load in wgs reads with weights_only=True (tensors and plain values, no code)."""
    import ast
    from pathlib import Path

    wgs_dir = Path(__file__).resolve().parents[1] / "wgs"
    loads = 0
    for p in wgs_dir.rglob("*.py"):
        assert "weights_only=False" not in p.read_text(), p
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Call) and ast.unparse(node.func) == "torch.load":
                loads += 1
                flags = {k.arg: k.value for k in node.keywords}
                assert isinstance(flags.get("weights_only"), ast.Constant) and flags["weights_only"].value is True, (
                    f"{p}:{node.lineno}"
                )
    assert loads >= 2


@pytest.mark.parametrize("debug", [False, True])
def test_unexpected_error_in_a_stage_is_one_line_and_a_log(ws, monkeypatch, capfd, debug):
    """A bug inside a stage: one `error:` line naming the log file in the workspace, exit 1, no
    traceback; --debug shows the traceback instead."""
    from wgs.cli import main

    def broken(*_args, **_kw):
        raise ZeroDivisionError("a fault injected\ninto the fine stage")

    monkeypatch.setattr("wgs.stages.fine.run.run_fine", broken)
    if debug:
        with pytest.raises(ZeroDivisionError):
            main([str(a) for a in wgs(ws, "--debug", "fine", "--force")])
        assert not (ws / "logs").exists()
        return
    line = expect_error(ws.parent, wgs(ws, "fine", "--force"), "unexpected ZeroDivisionError", "--debug", code=1)
    assert "a fault injected into the fine stage" in line
    (log,) = (ws / "logs").glob("error-*.log")
    assert str(log) in line
    text = log.read_text()
    assert "Traceback" in text and "ZeroDivisionError" in text and "command: wgs " in text
    assert Workspace(ws).manifest("fine") is not None  # the finished stage is kept
