"""The numba projection against the torch reference: values, hand-written gradients, gradcheck."""

import math

import pytest
import torch

from wgs.gaussians.project import project_gaussians
from wgs.gaussians.project_numba import project_gaussians_numba

W, H = 48, 40


def scene(n=500, dtype=torch.float64, seed=0):
    """Gaussians around, behind, beside and far off the camera; a few degenerate quaternions."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.5, 1.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[:3] = 0.0  # zero norm: identity rotation, no gradient
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 1.0 - 3.0)
    viewmat = torch.eye(4, dtype=dtype)
    c, s = math.cos(0.3), math.sin(0.3)
    viewmat[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=dtype)
    viewmat[2, 3] = 2.0
    K = torch.tensor([[50.0, 0, 23.0], [0, 52.0, 21.5], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, viewmat, K


def outputs(fn, means, quats, scales, viewmat, K):
    p = fn(means, quats, scales, viewmat, K, W, H)
    return p.means2d, p.conics, p.depths, p.extents, p.visible


def test_smoke_shapes_and_dtype():
    means, quats, scales, viewmat, K = scene(dtype=torch.float32)
    m2, con, d, ext, vis = outputs(project_gaussians_numba, means, quats, scales, viewmat, K)
    assert m2.shape == (500, 2) and con.shape == (500, 3) and d.shape == (500,) and ext.shape == (500, 2)
    assert m2.dtype == torch.float32 and vis.dtype == torch.bool
    assert 0 < int(vis.sum()) < 500  # the scene has culled and kept Gaussians


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_match_the_reference(dtype):
    args = scene(dtype=dtype)
    a = outputs(project_gaussians_numba, *args)
    b = outputs(project_gaussians, *args)
    assert torch.equal(a[4], b[4])
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    for x, y in zip(a[:4], b[:4], strict=True):
        assert torch.allclose(x, y, rtol=tol, atol=tol)


def test_gradients_match_the_reference():
    args = scene()
    g = torch.Generator().manual_seed(1)
    w_m, w_c = (
        torch.randn(500, 2, generator=g, dtype=torch.float64),
        torch.randn(500, 3, generator=g, dtype=torch.float64),
    )
    grads = []
    for fn in (project_gaussians_numba, project_gaussians):
        leaves = [t.clone().requires_grad_(True) for t in args[:3]]
        m2, con, *_ = outputs(fn, *leaves, *args[3:])
        ((m2 * w_m).sum() + (con * w_c).sum()).backward()
        grads.append([t.grad for t in leaves])
    for name, ga, gb in zip(("means", "quats", "scales"), *grads, strict=True):
        assert torch.allclose(ga, gb, rtol=1e-8, atol=1e-8 * gb.abs().max()), name
    assert grads[0][1][:3].abs().max() == 0  # zero quaternions get no gradient


def test_gradcheck_float64():
    torch.manual_seed(0)
    n = 6
    means = (torch.randn(n, 3, dtype=torch.float64) * 0.3).requires_grad_(True)
    means.data[0] = torch.tensor([3.0, 0.5, 0.0], dtype=torch.float64)  # x/z clamped at the border
    quats = torch.randn(n, 4, dtype=torch.float64).requires_grad_(True)
    scales = torch.rand(n, 3, dtype=torch.float64) * 0.2 + 0.05
    scales[0] = 0.8  # large enough to reach into the image
    scales.requires_grad_(True)
    viewmat, K = scene(dtype=torch.float64)[3:]

    def f(means, quats, scales):
        p = project_gaussians_numba(means, quats, scales, viewmat, K, W, H)
        return p.means2d, p.conics

    assert project_gaussians_numba(means, quats, scales, viewmat, K, W, H).visible.all()
    assert torch.autograd.gradcheck(f, (means, quats, scales), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_extreme_inputs_stay_finite():
    means, quats, scales, viewmat, K = scene(n=64, dtype=torch.float32)
    scales[:8] = 1e-7
    scales[8:16] = 1e3
    scales[16:24, 0] = 1e-4  # anisotropy 1e6 and more
    scales[16:24, 1:] = 1e2
    means[24:28] = torch.tensor([0.0, 0.0, -2.0 + 1e-9])  # on the camera centre
    means[28] = float("nan")
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    m2, con, d, ext, vis = outputs(project_gaussians_numba, *leaves, viewmat, K)
    ref = outputs(project_gaussians, means, quats, scales, viewmat, K)
    assert torch.equal(vis, ref[4])
    for t in (m2, con, ext):
        assert torch.isfinite(t).all()
    (m2.sum() + con.sum()).backward()
    for t in leaves:
        assert torch.isfinite(t.grad).all()


def test_rejects_a_camera_that_needs_gradients_by_using_the_reference():
    from wgs.gaussians.render import rasterize

    means, quats, scales, viewmat, K = scene(n=50, dtype=torch.float64)
    viewmat = viewmat.clone().requires_grad_(True)
    rgb, alpha, _ = rasterize(
        means,
        quats,
        scales,
        torch.full((50,), 0.5, dtype=torch.float64),
        torch.rand(50, 3, dtype=torch.float64),
        viewmat,
        K,
        W,
        H,
        backend="numba",
    )
    (rgb.sum() + alpha.sum()).backward()
    assert viewmat.grad is not None and torch.isfinite(viewmat.grad).all() and viewmat.grad.abs().sum() > 0
