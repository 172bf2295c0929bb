"""Stability suite, metrics: PSNR / SSIM on identical and constant images: defined, documented values.

Every case and its pass criterion is listed in docs/stability.md."""

import math

import pytest
import torch

from wgs.metrics import psnr, ssim


def test_ssim_and_psnr_defined_values():
    x = torch.rand(16, 16, 3)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    c = torch.full((16, 16, 3), 0.5)
    assert ssim(c, c) == pytest.approx(1.0)
    assert math.isfinite(ssim(c, torch.zeros_like(c)))
    assert psnr(x, x) == math.inf
    assert psnr(torch.zeros(4, 4), torch.ones(4, 4)) == pytest.approx(0.0)
    with pytest.raises(ValueError):
        ssim(torch.zeros(4, 4), torch.zeros(4, 4))
