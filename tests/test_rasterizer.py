"""Rasterizer: fast path vs pure-torch reference, gradcheck, hand-checked cases."""

import math

import pytest
import torch

from wgs.gaussians.project import project_gaussians, quat_to_rotmat
from wgs.gaussians.raster_torch import rasterize_pixels_torch
from wgs.gaussians.render import rasterize
from wgs.gaussians.synthetic import random_scene


def camera(size, f=None, dtype=torch.float32):
    f = f or size * 1.2
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[2, 3] = 2.5
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=dtype)
    return viewmat, K


def render_with_grads(backend, params, viewmat, K, w, h, bg, seed=1):
    ps = [p.detach().clone().requires_grad_(True) for p in params]
    rgb, alpha, meta = rasterize(*ps, viewmat, K, w, h, bg, backend=backend)
    g = torch.Generator().manual_seed(seed)
    wts = torch.rand(h, w, 3, generator=g, dtype=rgb.dtype)
    wa = torch.rand(h, w, 1, generator=g, dtype=rgb.dtype)
    ((rgb * wts).sum() + (alpha * wa).sum()).backward()
    return rgb.detach(), alpha.detach(), [p.grad for p in ps], meta


@pytest.mark.parametrize("n,size,w_scale", [(300, 40, -3.0), (2000, 48, -3.5), (1500, 37, -2.5)])
def test_fast_path_matches_reference(n, size, w_scale):
    means, quats, scales, opac, colors, viewmat, K = random_scene(n, size, seed=n)
    scales = torch.exp(torch.log(scales) - (-4.0) + w_scale)  # many overlaps
    params = [means, quats, scales, opac, colors]
    bg = torch.tensor([0.3, 0.6, 0.9])
    a = render_with_grads("numba", params, viewmat, K, size, size + 3, bg)
    b = render_with_grads("torch", params, viewmat, K, size, size + 3, bg)
    assert (a[0] - b[0]).abs().max() < 1e-5
    assert (a[1] - b[1]).abs().max() < 1e-5
    for name, ga, gb in zip(["means", "quats", "scales", "opacities", "colors"], a[2], b[2], strict=True):
        rel = ((ga - gb).norm() / gb.norm()).item()
        assert rel < 1e-4, (name, rel)
    ma, mb = a[3]["means2d"].grad, b[3]["means2d"].grad
    assert ((ma - mb).norm() / mb.norm()).item() < 1e-4


def test_fast_path_sh_and_depth():
    means, quats, scales, opac, _, viewmat, K = random_scene(400, 32, seed=3)
    sh = torch.randn(400, 9, 3, generator=torch.Generator().manual_seed(0)) * 0.3
    outs = [
        rasterize(means, quats, scales, opac, sh, viewmat, K, 32, 32, render_depth=True, backend=be)
        for be in ("numba", "torch")
    ]
    assert (outs[0][0] - outs[1][0]).abs().max() < 1e-5
    assert (outs[0][2]["depth"] - outs[1][2]["depth"]).abs().max() < 1e-4
    d = outs[0][2]["depth"] / outs[0][1].clamp_min(1e-6)
    assert ((d > 1.0) | (outs[0][1] < 0.5)).all()  # expected depth lies near the camera's 2.5 units


def test_reference_gradcheck_float64():
    torch.manual_seed(0)
    n, w, h = 4, 9, 8
    dt = torch.float64
    means = (torch.randn(n, 3, dtype=dt) * 0.15).requires_grad_(True)
    quats = torch.randn(n, 4, dtype=dt).requires_grad_(True)
    scales = (torch.rand(n, 3, dtype=dt) * 0.1 + 0.1).requires_grad_(True)
    opac = (torch.rand(n, dtype=dt) * 0.5 + 0.2).requires_grad_(True)
    colors = torch.rand(n, 3, dtype=dt).requires_grad_(True)
    viewmat, K = camera(w, f=12.0, dtype=dt)
    viewmat = viewmat.clone().requires_grad_(True)  # the pose is differentiable too

    def f(means, quats, scales, opac, colors, viewmat):
        rgb, alpha, _ = rasterize(
            means,
            quats,
            scales,
            opac,
            colors,
            viewmat,
            K,
            w,
            h,
            torch.tensor([0.1, 0.2, 0.3], dtype=dt),
            backend="torch",
        )
        return rgb, alpha

    assert torch.autograd.gradcheck(f, (means, quats, scales, opac, colors, viewmat), eps=1e-6, atol=1e-5)


def test_single_isotropic_gaussian_is_analytic():
    size, f, z, s, o = 33, 40.0, 2.5, 0.1, 0.5
    viewmat, K = camera(size, f=f, dtype=torch.float64)
    means = torch.zeros(1, 3, dtype=torch.float64)
    rgb, alpha, _ = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.full((1, 3), s, dtype=torch.float64),
        torch.tensor([o], dtype=torch.float64),
        torch.ones(1, 3, dtype=torch.float64),
        viewmat,
        K,
        size,
        size,
        backend="torch",
    )
    var = (f * s / z) ** 2 + 0.3  # EWA variance plus the 0.3 px² dilation
    ax = torch.arange(size, dtype=torch.float64) + 0.5
    ys, xs = torch.meshgrid(ax, ax, indexing="ij")
    r2 = (xs - size / 2) ** 2 + (ys - size / 2) ** 2
    expected = o * torch.exp(-0.5 * r2 / var)
    expected = torch.where((r2 / var <= 9) & (expected >= 1 / 255), expected, torch.zeros_like(expected))
    torch.testing.assert_close(alpha[..., 0], expected.to(alpha.dtype), atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(rgb[..., 0], expected.to(rgb.dtype), atol=1e-9, rtol=1e-9)
    fast = rasterize(
        means.float(),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.full((1, 3), s),
        torch.tensor([o]),
        torch.ones(1, 3),
        viewmat.float(),
        K.float(),
        size,
        size,
        backend="numba",
    )[1]
    torch.testing.assert_close(fast[..., 0], expected.float(), atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_two_opaque_gaussians_composite_in_depth_order(backend):
    size = 16
    viewmat, K = camera(size, f=20.0)
    means = torch.tensor([[0.0, 0, 0.5], [0.0, 0, -0.5]])  # second is nearer the camera
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 1.0)
    opac = torch.full((2,), 0.9)
    colors = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    rgb, alpha, _ = rasterize(means, quats, scales, opac, colors, viewmat, K, size, size, backend=backend)
    c = rgb[size // 2 - 1, size // 2 - 1]  # pixel centre 0.5 px from the means: Gaussian value ~1
    a_front = 0.9 * math.exp(-0.5 * 0.5 / ((20 / 2.0) ** 2 + 0.3))
    a_back = 0.9 * math.exp(-0.5 * 0.5 / ((20 / 3.0) ** 2 + 0.3))
    torch.testing.assert_close(c, torch.tensor([a_back * (1 - a_front), a_front, 0.0]), atol=1e-4, rtol=0)
    torch.testing.assert_close(
        alpha[size // 2 - 1, size // 2 - 1, 0], torch.tensor(1 - (1 - a_front) * (1 - a_back)), atol=1e-4, rtol=0
    )
    rgb2, _, _ = rasterize(means.flip(0), quats, scales, opac, colors.flip(0), viewmat, K, size, size, backend=backend)
    torch.testing.assert_close(rgb, rgb2)  # input order does not matter, depth does


def test_quaternion_convention_wxyz():
    q = torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]])  # 90° about z
    R = quat_to_rotmat(q)[0]
    torch.testing.assert_close(R @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)


def test_projection_culls_behind_and_offscreen():
    viewmat, K = camera(32)
    means = torch.tensor([[0.0, 0, 0], [0, 0, -3.0], [100.0, 0, 0], [0, 0, -2.5]])
    p = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]] * 4), torch.full((4, 3), 0.01), viewmat, K, 32, 32)
    assert p.visible.tolist() == [True, False, False, False]


def test_reference_rejects_bad_shapes():
    viewmat, K = camera(8)
    with pytest.raises(ValueError, match="quats"):
        rasterize(
            torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2), torch.ones(2, 3), viewmat, K, 8, 8
        )


def test_empty_scene_gives_background():
    viewmat, K = camera(8)
    bg = torch.tensor([0.2, 0.4, 0.6])
    for be in ("numba", "torch"):
        rgb, alpha, _ = rasterize(
            torch.zeros(0, 3),
            torch.zeros(0, 4),
            torch.zeros(0, 3),
            torch.zeros(0),
            torch.zeros(0, 3),
            viewmat,
            K,
            8,
            8,
            bg,
            backend=be,
        )
        assert torch.allclose(rgb, bg.expand(8, 8, 3)) and (alpha == 0).all()


def test_raster_pixels_direct_call_is_documented_shape():
    m = torch.tensor([[4.0, 4.0]])
    out, a = rasterize_pixels_torch(
        m,
        torch.tensor([[0.5, 0.0, 0.5]]),
        torch.ones(1, 2),
        torch.tensor([0.5]),
        torch.tensor([1.0]),
        torch.tensor([[5.0, 5.0]]),
        torch.tensor([True]),
        8,
        6,
        torch.zeros(2),
    )
    assert out.shape == (6, 8, 2) and a.shape == (6, 8, 1)


def test_fast_depth_order_is_the_stable_reference_order():
    from wgs.gaussians.raster_numba import _depth_order
    from wgs.gaussians.raster_torch import depth_order

    g = torch.Generator().manual_seed(0)
    depths = torch.randint(1, 50, (5000,), generator=g).float() / 7  # many ties: the order must stay stable
    visible = torch.rand(5000, generator=g) > 0.2
    assert (torch.from_numpy(_depth_order(depths, visible)) == depth_order(depths, visible)).all()
    assert (torch.from_numpy(_depth_order(depths.double(), visible)) == depth_order(depths, visible)).all()


def test_per_gaussian_sums_match_index_add():
    import numpy as np

    from wgs.gaussians.raster_numba import _sum_per_gaussian

    g = torch.Generator().manual_seed(1)
    ids = torch.randint(0, 300, (4000,), generator=g)
    rows = torch.randn(4000, 9, generator=g)
    order = torch.argsort(ids, stable=True)
    starts = torch.zeros(301, dtype=torch.int64)
    starts[1:] = torch.bincount(ids, minlength=300).cumsum(0)
    fast = _sum_per_gaussian(rows.numpy(), order.numpy().astype(np.int64), starts.numpy())
    assert torch.equal(torch.from_numpy(fast), torch.zeros(300, 9).index_add_(0, ids, rows))  # bit for bit
