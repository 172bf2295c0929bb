"""LightGlue's cross-attention fused on the CPU (`learned_matching.fused_cross_attention`) against
kornia's own forward, on a tiny block with random weights, and put in where kornia does not fuse it
itself; ALIKED channels-last against contiguous."""

import numpy as np
import pytest
import torch
from kornia.feature.lightglue import CrossBlock

from wgs.scene.learned_matching import fused_cross_attention


def tiny_block(dtype=torch.float64) -> CrossBlock:
    torch.manual_seed(0)
    return CrossBlock(embed_dim=16, num_heads=4).to(dtype).eval()


def test_smoke_shapes():
    block = tiny_block(torch.float32)
    x0, x1 = torch.randn(1, 7, 16), torch.randn(1, 5, 16)
    y0, y1 = fused_cross_attention(block, x0, x1)
    assert y0.shape == x0.shape and y1.shape == x1.shape


@pytest.mark.parametrize("m, n", [(7, 5), (1, 9), (33, 33)])
def test_equals_kornias_forward_in_float64(m, n):
    block = tiny_block()
    x0, x1 = torch.randn(2, m, 16, dtype=torch.float64), torch.randn(2, n, 16, dtype=torch.float64)
    want = CrossBlock.forward(block, x0, x1)
    got = fused_cross_attention(block, x0, x1)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_a_mask_takes_kornias_forward():
    block = tiny_block()
    x0, x1 = torch.randn(1, 4, 16, dtype=torch.float64), torch.randn(1, 6, 16, dtype=torch.float64)
    mask = torch.ones(1, 1, 4, 6, dtype=torch.bool)
    mask[..., -1] = False
    want = CrossBlock.forward(block, x0, x1, mask)
    got = fused_cross_attention(block, x0, x1, mask)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b)


def test_gradcheck_float64():
    block = tiny_block()
    x0 = torch.randn(1, 3, 16, dtype=torch.float64, requires_grad=True)
    x1 = torch.randn(1, 4, 16, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: fused_cross_attention(block, a, b), (x0, x1))


def test_the_fused_attention_goes_where_kornia_does_not_fuse_it():
    from wgs.scene import learned_matching as lm

    _, matcher = lm._models()
    for layer in matcher.transformers:
        patched = "forward" in vars(layer.cross_attn)
        assert patched != lm.kornia_fuses(layer.cross_attn)


def test_channels_last_extraction_finds_the_contiguous_models_keypoints():
    """ALIKED runs channels-last (faster on the CPU); the keypoints and descriptors are the
    contiguous model's, on a textured 192x256 image enlarged to MATCH_SIDE."""
    from wgs.scene import learned_matching as lm

    rng = np.random.default_rng(0)
    image = np.clip(rng.random((24, 32, 3)).repeat(8, 0).repeat(8, 1) + rng.normal(0, 0.02, (192, 256, 3)), 0, 1)
    fast = lm.extract(image)
    extractor, _ = lm._models()
    try:
        extractor.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload]
        reference = lm.extract(image)
    finally:
        extractor.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    assert len(fast.keypoints) > 100 and len(fast.keypoints) == len(reference.keypoints)
    np.testing.assert_allclose(fast.keypoints, reference.keypoints, atol=1e-3)
    torch.testing.assert_close(fast.descriptors, reference.descriptors, rtol=1e-3, atol=1e-4)
