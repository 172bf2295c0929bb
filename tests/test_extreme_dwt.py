"""Stability suite, dwt: Haar DWT at extreme magnitudes (1e-30 .. 1e38) in float32 and float64: reconstruction
error bounds.

Every case and its pass criterion is listed in docs/stability.md."""

import pytest
import torch
from test_haar import rel_err

from wgs.wavelet.haar import dwt2, idwt2


@pytest.mark.parametrize("exponent", [-30, -10, 0, 10, 30])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
def test_extreme_magnitudes(exponent, dtype, tol):
    g = torch.Generator().manual_seed(1)
    x = (torch.rand(1, 3, 21, 22, generator=g, dtype=torch.float64) + 0.5) * 10.0**exponent
    x = x.to(dtype)
    ll, highs = dwt2(x, 3)
    y = idwt2(ll, highs, size=(21, 22))
    assert torch.isfinite(y).all()
    assert rel_err(y, x) <= tol


def test_float32_near_max_does_not_overflow():
    # LL = 2 * block mean, so 1e38 (LL 2e38 < 3.4e38) must survive: sums are formed of halves.
    x = torch.full((1, 1, 4, 4), 1e38, dtype=torch.float32)
    x[..., 1::2, :] = -1e38
    ll, highs = dwt2(x, 1)
    assert torch.isfinite(ll).all() and all(torch.isfinite(h).all() for h in highs[0])
    assert rel_err(idwt2(ll, highs), x) < 1e-6
