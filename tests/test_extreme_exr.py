"""Stability suite, exr: Subband EXR files beyond the half-float range: clamped with a warning, non-finite
values refused.

Every case and its pass criterion is listed in docs/stability.md."""

import numpy as np
import pytest

from wgs.io.exr import read_subbands, write_subbands


def test_half_range_clamped_with_warning(tmp_path):
    b = {"LL": np.array([[[1e6, -1e6, 3.0]]], np.float32)}
    with pytest.warns(UserWarning, match="clamped"):
        write_subbands(tmp_path / "h.exr", b)
    out = read_subbands(tmp_path / "h.exr")["LL"]
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(out[0, 0], [65504.0, -65504.0, 3.0])


def test_refuses_non_finite(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        write_subbands(tmp_path / "n.exr", {"LL": np.full((2, 2, 3), np.nan, np.float32)})
    assert not (tmp_path / "n.exr").exists()
