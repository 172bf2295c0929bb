"""Subband EXR files: bit-exact round trips, channel order, half-range clamping, corrupt files."""

import numpy as np
import pytest

from wgs.errors import InputError
from wgs.io.exr import read_subbands, write_subbands


def bands(rng, h=9, w=7, dtype=np.float32):
    return {n: rng.normal(size=(h, w, 3)).astype(dtype) for n in ("LL", "LH", "HL", "HH")}


def test_float_roundtrip_bit_exact(tmp_path):
    b = bands(np.random.default_rng(0))
    write_subbands(tmp_path / "a.exr", b, half=False)
    out = read_subbands(tmp_path / "a.exr")
    assert list(out) == ["LL", "LH", "HL", "HH"]
    for k in b:
        assert out[k].dtype == np.float32
        np.testing.assert_array_equal(out[k], b[k])


def test_half_roundtrip_bit_exact(tmp_path):
    b = {k: v.astype(np.float16).astype(np.float32) for k, v in bands(np.random.default_rng(1)).items()}
    write_subbands(tmp_path / "a.exr", b)
    out = read_subbands(tmp_path / "a.exr")
    for k in b:
        np.testing.assert_array_equal(out[k], b[k])


def test_channel_order_preserved(tmp_path):
    # distinct constant per channel, names that sort differently from insertion order
    b = {
        "ZZ": np.zeros((2, 3, 3), np.float32),
        "AA": np.ones((2, 3, 3), np.float32),
        "M": np.zeros((2, 3, 1), np.float32),
    }
    b["ZZ"][..., :] = [1, 2, 3]
    b["AA"][..., :] = [4, 5, 6]
    b["M"][...] = 7
    write_subbands(tmp_path / "c.exr", b, half=False)
    out = read_subbands(tmp_path / "c.exr")
    np.testing.assert_array_equal(out["ZZ"][0, 0], [1, 2, 3])
    np.testing.assert_array_equal(out["AA"][0, 0], [4, 5, 6])
    assert out["M"].shape == (2, 3, 1) and out["M"][0, 0, 0] == 7


@pytest.mark.parametrize("damage", ["truncate", "garbage", "missing"])
def test_corrupt_file_clear_error(tmp_path, damage):
    p = tmp_path / "x.exr"
    write_subbands(p, bands(np.random.default_rng(2), 64, 64), half=False)
    if damage == "truncate":
        p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    elif damage == "garbage":
        p.write_bytes(b"not an exr at all" * 10)
    else:
        p.unlink()
    with pytest.raises(InputError) as exc:
        read_subbands(p)
    assert str(p) in str(exc.value)
