"""Shared fixtures: small generated scenes in every supported format."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
LEGO = ROOT.parent / "shared" / "data" / "lego"
# tests/cluster starts a real Slurm (root, Debian's packages): `make test-cluster` runs it, `make test` not
collect_ignore = [] if os.environ.get("WGS_TEST_CLUSTER") == "1" else ["cluster"]
# a fixed thread count: the tests compare reruns bit for bit, and sums depend on the thread count
# (wgs otherwise adapts it to other processes' load, see wgs/threads.py); under pytest-xdist
# (`make test` runs one worker per core) each worker takes one core
if os.environ.get("PYTEST_XDIST_WORKER"):  # a worker inherits the controller's settings: replace them
    from wgs.threads import COUNT_VARS

    share = str(max(1, len(os.sched_getaffinity(0)) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    for key in ("WGS_THREADS", *COUNT_VARS):
        os.environ[key] = share
else:
    os.environ.setdefault("WGS_THREADS", str(len(os.sched_getaffinity(0))))
# No LPIPS weights in the tests, whatever this machine holds (tests that want them bring their own):
# results then say "lpips": null and why, the same everywhere.
os.environ["TORCH_HOME"] = tempfile.mkdtemp(prefix="wgs-tests-torch-home-")
os.environ["WGS_CACHE"] = tempfile.mkdtemp(prefix="wgs-tests-cache-")  # one run-time calibration for the suite
os.environ.pop("WGS_LPIPS_WEIGHTS", None)

# The smallest config that runs every stage (seconds per `wgs all` on a 48-64 px scene).
TINY = """
[prepare]
mirror = "none"  # the photos alone; tests/test_end_to_end.py runs the mirror views on their own
[coarse]
iterations = 30
refine_start = 10
refine_every = 10
init_points = 800
hull_resolution = 32
ensemble = 2
stop = "iterations"  # all 30 iterations, no pilots; TINY_HELD_OUT keeps the default rule
[mask_data]
iterations = 30
refine_start = 10
refine_every = 10
init_points = 800
hull_resolution = 32
warmup = 10
pair_every = 10
[finetune]
d_steps = 8
d_channels = 8
d_batch = 4
u_max_steps = 8
u_channels = 8
u_eval_every = 4
eval_steps = 2
prior_steps = 4
prior_eval_every = 2
[repair]
steps = 2
num_views = 16
hull_resolution = 32
[fine]
iterations = 20
refine_start = 5
refine_every = 5
hull_resolution = 32
[eval]
turntable_frames = 8
hull_resolution = 32
"""

# TINY with one coarse model: for tests of what runs the pipeline (batch, ablate), where a second
# model only adds the start-up of the processes that train the ensemble side by side
TINY_ONE_MODEL = TINY.replace("ensemble = 2", "ensemble = 1")
assert TINY_ONE_MODEL != TINY
# TINY with the coarse stage's default stopping rule (pilots that each hold out a photo): the
# session's finished workspace and tests/test_stopping.py
TINY_HELD_OUT = re.sub(r'stop = "iterations".*\n', "", TINY, count=1)
assert TINY_HELD_OUT != TINY and "stop =" not in TINY_HELD_OUT

from make_scene import make_scene  # noqa: E402

from wgs.io.images import read_image, write_png  # noqa: E402
from wgs.scene.convention import GL_TO_CV, invert_rigid  # noqa: E402
from wgs.scene.formats import read_scene  # noqa: E402
from wgs.scene.orbit import look_at  # noqa: E402


@pytest.fixture(scope="session")
def blender_scene(tmp_path_factory) -> Path:
    """The bundled example generator at 48x48: 4 train + 6 test views."""
    return make_scene(tmp_path_factory.mktemp("blender") / "scene", seed=1, size=48, n_train=4, n_test=6)


def blender_views(src: Path):
    """(name, rgb [H,W,3], alpha [H,W], K, w2c) of all views of a Blender scene."""
    raw = read_scene(src)
    out = []
    for v in raw.views:
        img = read_image(v.image)
        out.append((v.name, img[..., :3], img[..., 3], v.K, v.w2c))
    return out


def to_colmap(src: Path, dst: Path) -> Path:
    """Write the Blender scene as a COLMAP scene (sparse/0 text model, images/, masks/)."""
    import torch

    from wgs.scene.camera import Camera
    from wgs.scene.colmap import write_model

    views = blender_views(src)
    for name, rgb, alpha, _, _ in views:
        write_png(dst / "images" / name, rgb)
        write_png(dst / "masks" / name, alpha)
    write_model(
        dst / "sparse" / "0",
        {v[0]: Camera(torch.from_numpy(v[3]), torch.from_numpy(v[4]), v[1].shape[1], v[1].shape[0]) for v in views},
    )
    return dst


def to_ngp(src: Path, dst: Path) -> Path:
    views = blender_views(src)
    frames = []
    for name, rgb, alpha, _, w2c in views:
        write_png(dst / "images" / name, rgb)
        write_png(dst / "masks" / name, alpha)
        c2w = invert_rigid(w2c) @ GL_TO_CV  # back to OpenGL
        frames.append({"file_path": f"images/{name}", "mask_path": f"masks/{name}", "transform_matrix": c2w.tolist()})
    K = views[0][3]
    h, w = views[0][1].shape[:2]
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h, "frames": frames}
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def to_idr(src: Path, dst: Path) -> Path:
    views = blender_views(src)
    cams = {}
    for i, (_, rgb, alpha, K, w2c) in enumerate(views):
        write_png(dst / "image" / f"{i:03d}.png", rgb)
        write_png(dst / "mask" / f"{i:03d}.png", alpha)
        P = np.eye(4)
        P[:3, :4] = 2.5 * (K @ w2c[:3, :4])  # projection matrices are defined up to scale
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = np.eye(4)
    np.savez(dst / "cameras_sphere.npz", **cams)
    return dst


@pytest.fixture(scope="session")
def scene_formats(blender_scene, tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("formats")
    return {
        "blender": blender_scene,
        "colmap": to_colmap(blender_scene, base / "colmap"),
        "ngp": to_ngp(blender_scene, base / "ngp"),
        "idr": to_idr(blender_scene, base / "idr"),
    }


@pytest.fixture(scope="session")
def finished_workspace(tmp_path_factory) -> tuple[Path, str]:
    """One tiny `wgs all` for the whole session: (folder with scene/, wgs.toml (TINY_HELD_OUT) and ws/, the
    command's output). Tests copy ws/ before they change anything in it."""
    from click.testing import CliRunner

    from wgs.cli import cli

    base = tmp_path_factory.mktemp("finished")
    scene = make_scene(base / "scene", seed=2, size=64, n_train=4, n_test=5)
    (base / "wgs.toml").write_text(TINY_HELD_OUT)
    res = CliRunner().invoke(
        cli,
        ["-q", "--config", str(base / "wgs.toml"), "-w", str(base / "ws"), "all", str(scene)],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    return base, res.output


@pytest.fixture
def scene_copy(blender_scene, tmp_path) -> Path:
    """A writable copy of the example scene, for tests that break it."""
    dst = tmp_path / "scene"
    shutil.copytree(blender_scene, dst)
    return dst


def lego_or_skip() -> Path:
    if not (LEGO / "transforms_train.json").is_file():
        pytest.skip("shared lego data not present")
    return LEGO


def run_cli(args, cwd: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    """Run `wgs` in a subprocess, as a shell would (main() maps errors to exit codes): for what only a
    process shows (a native library's own stderr, resource limits, signals, a pool of children)."""
    return subprocess.run(
        [sys.executable, "-m", "wgs", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=timeout
    )


def run_wgs(args, cwd: Path) -> subprocess.CompletedProcess:
    """Run `wgs` in this process through `wgs.cli.main`, the entry point's error mapping: its exit code,
    stdout and stderr as `run_cli` gives them (a subprocess adds the imports, about 2 s, and torch's
    compiler stack that its optimizers load, 1.3 s); an unexpected exception fails the test with
    its traceback."""
    import contextlib
    import io

    from wgs.cli import main

    out_buf, err_buf = io.StringIO(), io.StringIO()
    with contextlib.chdir(cwd), contextlib.redirect_stderr(err_buf), contextlib.redirect_stdout(out_buf):
        try:
            main([str(a) for a in args])
            returncode = 0
        except SystemExit as exc:
            returncode = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(["wgs", *map(str, args)], returncode, out_buf.getvalue(), err_buf.getvalue())


def expect_error(cwd: Path, args, *needles: str, code: int = 2) -> str:
    """The command fails with `code` and exactly one `error:` line holding every needle, no traceback
    (`run_wgs`, in this process)."""
    proc = run_wgs(args, cwd)
    err = proc.stderr.strip()
    assert proc.returncode == code, (proc.returncode, err)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def generated_frames(obj, eyes: dict[str, list[np.ndarray]], size: int) -> dict[str, list]:
    """make_scene's object `obj` rendered from camera positions (world, looking at the origin) per
    split: {split: [Frame with image and mask]} in the normalised world of the "train" cameras."""
    import make_scene as ms
    import torch

    from wgs.scene.convention import c2w_opengl_to_w2c_opencv, focal_from_fov, normalisation_from_cameras
    from wgs.scene.dataset import Frame

    w2cs = {k: [c2w_opengl_to_w2c_opencv(ms.look_at_c2w(e)) for e in v] for k, v in eyes.items()}
    norm = normalisation_from_cameras(w2cs["train"])
    f = focal_from_fov(ms.FOV_X, size)
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    out = {}
    for k, v in eyes.items():
        out[k] = []
        for i, eye in enumerate(v):
            rgba = torch.from_numpy(ms.render(obj, ms.look_at_c2w(eye), size).astype(np.float32))
            w2c = torch.tensor(norm.w2c_to_normalised(w2cs[k][i]), dtype=torch.float32)
            out[k].append(Frame(K, w2c, size, size, name=f"{k}_{i}.png", image=rgba[..., :3], mask=rgba[..., 3]))
    return out


def ring_w2c(n=4, radius=1.0, height=0.3, jitter=0.0, seed=0):
    """World-to-camera matrices of n cameras on a ring looking at the origin."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n + jitter * rng.normal()
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height * radius])
        out.append(look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])))
    return out


def pytest_collection_modifyitems(config, items):
    """The tests marked slow first (longest first, as a scheduler would have them): with one
    pytest-xdist worker per core, a long test started last would keep one worker busy while the
    others have finished."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
