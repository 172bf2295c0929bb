"""The file layer: PLY and checkpoint containers (images and EXR have their own test files)."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from wgs.errors import InputError
from wgs.io.checkpoint import UnreadableCheckpoint, read_checkpoint, write_checkpoint
from wgs.io.ply import read_ply, write_ply


def test_ply_round_trip_keeps_names_order_and_bits(tmp_path):
    names = ["x", "y", "z", "opacity"]
    data = np.random.default_rng(0).normal(size=(7, 4)).astype(np.float32)
    data[3, 1] = np.float32(1e-38)  # a subnormal survives: the bytes are copied, not printed
    write_ply(tmp_path / "a.ply", names, data)
    got_names, got = read_ply(tmp_path / "a.ply")
    assert got_names == names and got.dtype == np.float32 and np.array_equal(got, data)


def test_ply_with_no_vertices(tmp_path):
    write_ply(tmp_path / "e.ply", ["x"], np.zeros((0, 1), np.float32))
    names, data = read_ply(tmp_path / "e.ply")
    assert names == ["x"] and data.shape == (0, 1)


def test_ply_shape_must_match_names(tmp_path):
    with pytest.raises(ValueError, match="2 properties"):
        write_ply(tmp_path / "b.ply", ["x", "y"], np.zeros((3, 3), np.float32))
    assert not (tmp_path / "b.ply").exists()


@pytest.mark.parametrize(
    "body, needle",
    [
        (b"solid cube\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n", "binary little-endian"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty uchar x\nend_header\n\x01",
            "float properties",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nend_header\n\0\0\0\0",
            "truncated",
        ),
    ],
)
def test_bad_ply_names_the_file(tmp_path, body, needle):
    p = tmp_path / "bad.ply"
    p.write_bytes(body)
    with pytest.raises(InputError, match=needle) as err:
        read_ply(p)
    assert "bad.ply" in str(err.value)


def test_checkpoint_round_trip(tmp_path):
    state = {"step": 3, "t": torch.arange(5.0), "nested": {"a": [1, 2]}}
    write_checkpoint(tmp_path / "c.pt", state)
    got = read_checkpoint(tmp_path / "c.pt")
    assert got["step"] == 3 and torch.equal(got["t"], state["t"]) and got["nested"] == {"a": [1, 2]}


class Payload:
    def __reduce__(self):
        return (print, ("code ran",))


def test_checkpoint_with_code_is_refused_unrun(tmp_path, capsys):
    torch.save({"x": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(UnreadableCheckpoint):
        read_checkpoint(tmp_path / "evil.pt")
    assert "code ran" not in capsys.readouterr().out


@pytest.mark.parametrize("content", [None, b"", b"PK\x03\x04 truncated"])
def test_missing_or_damaged_checkpoint(tmp_path, content):
    p = tmp_path / "d.pt"
    if content is not None:
        p.write_bytes(content)
    with pytest.raises(UnreadableCheckpoint):
        read_checkpoint(p)


def test_plain_io_import_loads_neither_torch_nor_openimageio():
    code = "import sys, wgs.io; print('torch' in sys.modules, 'OpenImageIO' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
