"""Haar DWT: smoke, exceptions, features (exactness, PyWavelets naming), gradcheck."""

import numpy as np
import pytest
import torch

from wgs.wavelet.haar import dwt2, idwt2, split_highs, stack_highs


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double(), b.double()  # the norm of 1e30-sized float32 values overflows in float32
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


@pytest.mark.parametrize("levels", [1, 2, 3, 4])
@pytest.mark.parametrize("size", [(32, 32), (33, 17), (1, 1), (5, 64), (31, 1)])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
def test_perfect_reconstruction(levels, size, dtype, tol):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, *size, generator=g, dtype=dtype)
    ll, highs = dwt2(x, levels)
    assert len(highs) == levels
    assert rel_err(idwt2(ll, highs, size=size), x) <= tol


def test_orthonormal_energy_preserved():
    x = torch.randn(1, 2, 16, 16, dtype=torch.float64)
    ll, highs = dwt2(x, 2)
    energy = ll.pow(2).sum() + sum(b.pow(2).sum() for h in highs for b in h)
    assert torch.allclose(energy, x.pow(2).sum(), rtol=1e-12)


def test_matches_pywavelets():
    pywt = pytest.importorskip("pywt")
    x = np.random.default_rng(0).normal(size=(12, 10))
    cA, (cH, cV, cD) = pywt.dwt2(x, "haar")
    ll, [(lh, hl, hh)] = dwt2(torch.from_numpy(x)[None, None], 1)
    for ours, ref in ((ll, cA), (lh, cH), (hl, cV), (hh, cD)):
        np.testing.assert_allclose(ours[0, 0].numpy(), ref, atol=1e-12)


def test_matches_pywavelets_multilevel():
    pywt = pytest.importorskip("pywt")
    x = np.random.default_rng(1).normal(size=(16, 16))
    coeffs = pywt.wavedec2(x, "haar", level=3)
    ll, highs = dwt2(torch.from_numpy(x)[None, None], 3)
    np.testing.assert_allclose(ll[0, 0].numpy(), coeffs[0], atol=1e-12)
    for j in range(3):  # pywt lists the coarsest level first, we list the finest first
        for ours, ref in zip(highs[j], coeffs[3 - j], strict=True):
            np.testing.assert_allclose(ours[0, 0].numpy(), ref, atol=1e-12)


def test_gradcheck_float64():
    x = torch.randn(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)

    def f(x):
        ll, highs = dwt2(x, 2)
        return (ll, *highs[0], *highs[1])

    assert torch.autograd.gradcheck(f, (x,))
    ll, highs = dwt2(x.detach(), 2)
    ll.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: idwt2(a, highs, size=(5, 6)), (ll,))


def test_stack_split_highs():
    x = torch.randn(2, 3, 8, 8)
    _, [h] = dwt2(x)
    s = stack_highs(h)
    assert s.shape == (2, 9, 4, 4)
    for a, b in zip(split_highs(s), h, strict=True):
        assert torch.equal(a, b)


def test_exceptions():
    with pytest.raises(ValueError, match=r"\[B, C, H, W\]"):
        dwt2(torch.zeros(3, 8, 8))
    with pytest.raises(ValueError, match="levels"):
        dwt2(torch.zeros(1, 1, 8, 8), 0)
    ll, [h] = dwt2(torch.zeros(1, 1, 8, 8))
    with pytest.raises(ValueError, match="subband"):
        idwt2(ll, [(h[0], h[1], torch.zeros(1, 1, 3, 3))])
