"""Spherical harmonics checked without the code's own constants: each degree's basis functions are
orthonormal on the sphere and harmonic (their degree-l polynomial extensions have zero Laplacian),
in float64; degree 1 matches 3DGS's ordering and signs (-y, z, -x)."""

import math

import numpy as np
import pytest
import torch

from wgs.gaussians.sh import eval_sh, num_sh_bases


def basis(dirs: torch.Tensor, degree: int = 3) -> torch.Tensor:
    """[N, 3] directions -> [N, (degree+1)^2] basis values (one-hot coefficients)."""
    k = num_sh_bases(degree)
    sh = torch.eye(k, dtype=dirs.dtype)[None, :, :].expand(dirs.shape[0], k, k)  # colour channel j = basis j
    return eval_sh(sh, dirs, degree)


def sphere_quadrature(n_theta: int = 12, n_phi: int = 24):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for polynomials of degree < 2 n_theta."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3)
    weights = (w[:, None] * np.full(n_phi, 2 * math.pi / n_phi)[None, :]).reshape(-1)
    return torch.from_numpy(dirs), torch.from_numpy(weights)


def test_basis_is_orthonormal_on_the_sphere():
    dirs, w = sphere_quadrature()
    Y = basis(dirs)
    gram = (Y * w[:, None]).T @ Y
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-12)


@pytest.mark.parametrize("index, degree", [(i, int(math.isqrt(i))) for i in range(16)])
def test_each_basis_function_is_a_harmonic_polynomial_of_its_degree(index, degree):
    """p(v) = |v|^l Y(v / |v|) has zero Laplacian: Y lies in the degree-l harmonics."""
    g = torch.Generator().manual_seed(index)
    v = (torch.randn(8, 3, generator=g, dtype=torch.float64) * 0.7).requires_grad_(True)

    def p(x):
        return x.norm(dim=-1) ** degree * basis(x)[:, index]

    grad = torch.autograd.grad(p(v).sum(), v, create_graph=True)[0]
    lap = sum(torch.autograd.grad(grad[:, i].sum(), v, retain_graph=True)[0][:, i] for i in range(3))
    assert lap.abs().max() < 1e-9


def test_degree_one_ordering_and_signs_match_3dgs():
    c1 = math.sqrt(3 / (4 * math.pi))
    for d, expect in (([1.0, 0, 0], [0, 0, -c1]), ([0, 1.0, 0], [-c1, 0, 0]), ([0, 0, 1.0], [0, c1, 0])):
        y = basis(torch.tensor([d], dtype=torch.float64), 1)[0, 1:4]
        assert torch.allclose(y, torch.tensor(expect, dtype=torch.float64), atol=1e-15)
    assert basis(torch.tensor([[0.0, 0, 1]], dtype=torch.float64), 0)[0, 0] == pytest.approx(1 / math.sqrt(4 * math.pi))


def test_only_the_first_degree_coefficients_are_used():
    dirs = torch.randn(5, 3, dtype=torch.float64)
    sh = torch.randn(5, 16, 3, dtype=torch.float64)
    low = eval_sh(sh, dirs, 1)
    sh[:, 4:] = 0
    assert torch.equal(low, eval_sh(sh, dirs, 1)) and torch.allclose(low, eval_sh(sh, dirs, 3))
