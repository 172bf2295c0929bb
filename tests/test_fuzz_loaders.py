"""Fuzzing of the scene loaders with hypothesis: COLMAP text models, transforms.json (Blender and
instant-ngp), IDR camera npz files, split files. Whatever the bytes, a loader returns a scene or
raises InputError (one line naming the file); nothing else may escape.

Examples per test: 400 in `make test` (profile "ci"), 5000 in `make stress` (HYPOTHESIS_PROFILE=stress).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import string
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import to_colmap, to_idr, to_ngp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wgs.errors import InputError
from wgs.scene.formats import read_scene
from wgs.scene.splits import choose_split

pytestmark = pytest.mark.slow  # `pytest -m 'not slow'` for a quick loop; make test runs all

common = {
    "deadline": None,
    "suppress_health_check": [HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    "derandomize": True,
}
settings.register_profile("ci", max_examples=400, **common)
settings.register_profile("stress", max_examples=5000, **common)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def load(root: Path, views: int | None = 3) -> None:
    """The whole import up to the split; must return or raise InputError."""
    scene = read_scene(root)
    choose_split(scene, views, 8)


def check(root: Path, views: int | None = 3) -> None:
    try:
        load(root, views)
    except InputError as exc:
        text = str(exc)
        assert "\n" not in text.strip() and text.strip(), repr(text)


@pytest.fixture(scope="module")
def bases(blender_scene, tmp_path_factory):
    base = tmp_path_factory.mktemp("fuzz")
    return {
        "colmap": to_colmap(blender_scene, base / "colmap"),
        "ngp": to_ngp(blender_scene, base / "ngp"),
        "idr": to_idr(blender_scene, base / "idr"),
        "blender": blender_scene,
    }


@pytest.fixture
def work(tmp_path):
    """A fresh scratch copy of a base scene for every example."""

    def copy(src: Path) -> Path:
        dst = tmp_path / "scene"
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src, dst)
        return dst

    return copy


# ----------------------------------------------------------------------------- byte-level mutations
@st.composite
def mutated(draw, original: bytes) -> bytes:
    """Truncations, deletions, insertions and byte flips of a valid file."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["truncate", "delete", "insert", "flip", "dup"]))
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        if op == "truncate":
            del data[i:]
        elif op == "delete":
            del data[i : i + draw(st.integers(1, 64))]
        elif op == "insert":
            data[i:i] = draw(
                st.binary(min_size=1, max_size=16)
                | st.sampled_from(
                    [b"nan", b"-inf", b"1e999", b" ", b"\n", b"\x00", b"..", b"/", b"-1", b"0", b"\xff\xfe"]
                )
            )
        elif op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        else:
            j = draw(st.integers(i, min(len(data), i + 200)))
            data[j:j] = data[i:j]
    return bytes(data)


def copy_and_pick(data, work, base: Path, rel: str) -> tuple[Path, Path, bytes, bool]:
    """A scratch copy of `base`; the file to fuzz, its original bytes, and whether to mutate bytes
    (True, done here) or the structure (False, left to the caller)."""
    root = work(base)
    original = (base / rel).read_bytes()
    by_bytes = data.draw(st.booleans(), label="mutate bytes")
    if by_bytes:
        (root / rel).write_bytes(data.draw(mutated(original), label=rel))
    return root, root / rel, original, by_bytes


# ----------------------------------------------------------------------------- COLMAP text models
def colmap_token():
    return st.one_of(
        st.integers(-3, 10).map(str),
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.sampled_from(["PINHOLE", "SIMPLE_RADIAL", "OPENCV", "FISHEYE", "UNKNOWN", "", "#"]),
        st.text(string.ascii_letters + "./_-", min_size=1, max_size=12),
    )


@given(data=st.data())
def test_fuzz_colmap_text(bases, work, data):
    root = work(bases["colmap"])
    model = root / "sparse" / "0"
    for name in ("cameras.txt", "images.txt"):
        original = (bases["colmap"] / "sparse" / "0" / name).read_bytes()
        if data.draw(st.booleans(), label=f"mutate {name} by bytes"):
            (model / name).write_bytes(data.draw(mutated(original), label=name))
        elif data.draw(st.booleans(), label=f"replace a line of {name}"):
            lines = original.decode().splitlines()
            k = data.draw(st.integers(0, len(lines) - 1))
            lines[k] = " ".join(data.draw(st.lists(colmap_token(), max_size=12), label="tokens"))
            (model / name).write_text("\n".join(lines) + "\n")
    check(root)


# ----------------------------------------------------------------------------- transforms.json
def json_value(leaf):
    return st.recursive(
        leaf, lambda c: st.lists(c, max_size=5) | st.dictionaries(st.text(max_size=8), c, max_size=5), max_leaves=20
    )


leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=False),
    st.text(max_size=20),
    st.sampled_from(["..", "../x.png", "/etc/passwd", "images/r_0.png"]),
)


def matrix():
    row = st.lists(st.one_of(st.floats(-1e6, 1e6), st.sampled_from([0.0, 1.0, -1.0, 1e308])), min_size=3, max_size=5)
    return st.lists(row, min_size=3, max_size=5)


@st.composite
def ngp_meta(draw, valid: dict) -> dict:
    meta = json.loads(json.dumps(valid))
    for key in draw(
        st.lists(
            st.sampled_from(["fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "k1", "p1", "frames"]),
            max_size=4,
            unique=True,
        )
    ):
        meta[key] = draw(json_value(leaves))
    frames = meta.get("frames")
    if isinstance(frames, list):
        for f in frames:
            if isinstance(f, dict) and draw(st.booleans()):
                key = draw(st.sampled_from(["file_path", "mask_path", "transform_matrix", "fl_x"]))
                f[key] = draw(matrix() if key == "transform_matrix" else json_value(leaves))
    return meta


@given(data=st.data())
def test_fuzz_ngp_transforms(bases, work, data):
    root, path, original, by_bytes = copy_and_pick(data, work, bases["ngp"], "transforms.json")
    if not by_bytes:
        path.write_text(json.dumps(data.draw(ngp_meta(json.loads(original)))))
    check(root, views=None)


@given(data=st.data())
def test_fuzz_blender_transforms(bases, work, data):
    split = data.draw(st.sampled_from(["train", "test"]), label="split")
    root, path, original, by_bytes = copy_and_pick(data, work, bases["blender"], f"transforms_{split}.json")
    if not by_bytes:
        meta = json.loads(original)
        if data.draw(st.booleans(), label="angle"):
            meta["camera_angle_x"] = data.draw(json_value(leaves) | st.floats())
        for f in meta["frames"]:
            if data.draw(st.booleans()):
                key = data.draw(st.sampled_from(["file_path", "transform_matrix"]))
                f[key] = data.draw(matrix() if key == "transform_matrix" else json_value(leaves))
        path.write_text(json.dumps(meta, allow_nan=True))
    check(root)


# ----------------------------------------------------------------------------- IDR npz
def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


arrays = st.one_of(
    st.just(np.eye(4)),
    st.lists(st.floats(), min_size=16, max_size=16).map(lambda v: np.array(v).reshape(4, 4)),
    st.integers(0, 3).map(lambda n: np.zeros((n, 4))),
    st.sampled_from(
        [
            np.array("text"),
            np.zeros((4, 4), dtype=np.int8),
            np.full((4, 4), np.nan),
            np.ones((2, 2, 2)),
            np.array([1 + 2j] * 16).reshape(4, 4),
            np.zeros((4, 4)),
            np.array([object()], dtype=object),
        ]
    ),
)


@given(data=st.data())
def test_fuzz_idr_cameras(bases, work, data):
    root, path, original, by_bytes = copy_and_pick(data, work, bases["idr"], "cameras_sphere.npz")
    if not by_bytes:
        with np.load(io.BytesIO(original)) as z:
            cams = {k: z[k] for k in z.files}
        for key in data.draw(st.lists(st.sampled_from(sorted(cams) + ["world_mat_9", "junk"]), max_size=4)):
            if data.draw(st.booleans()):
                cams.pop(key, None)
            else:
                cams[key] = data.draw(arrays)
        try:
            blob = npz_bytes(cams)
        except ValueError:  # numpy itself refuses some object arrays
            return
        path.write_bytes(blob)
    check(root)


def test_idr_npz_that_is_a_zip_of_junk(bases, work):
    root = work(bases["idr"])
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("world_mat_0.npy", b"\x93NUMPY junk")
    (root / "cameras_sphere.npz").write_bytes(buf.getvalue())
    with pytest.raises(InputError, match="cameras_sphere.npz"):
        load(root)


# ----------------------------------------------------------------------------- split files
@given(
    text=st.one_of(
        st.text(max_size=60), st.lists(st.integers(-5, 20), max_size=12).map(lambda ids: " ".join(map(str, ids)))
    ),
    raw=st.binary(max_size=40),
    use_raw=st.booleans(),
    which=st.sampled_from(["sparse_3.txt", "sparse_test.txt"]),
)
def test_fuzz_split_files(bases, work, text, raw, use_raw, which):
    root = work(bases["blender"])
    path = root / which
    if use_raw:
        path.write_bytes(raw)
    else:
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
    check(root)
