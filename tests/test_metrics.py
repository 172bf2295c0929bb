"""Metrics: 3DGS-style SSIM against a float64 reference, PSNR edge cases, LPIPS from local weights."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from wgs.lpips import LPIPS, LpipsUnavailable
from wgs.metrics import ssim, ssim_map, ssim_map_fast


def ssim_reference(a: np.ndarray, b: np.ndarray) -> float:
    """Direct float64 loop over pixels: zero-padded 11x11 Gaussian window, sigma 1.5."""
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    h, wd, c = a.shape
    pa = np.pad(a, ((5, 5), (5, 5), (0, 0)))
    pb = np.pad(b, ((5, 5), (5, 5), (0, 0)))
    total = 0.0
    for ch in range(c):
        for i in range(h):
            for j in range(wd):
                wa, wb = pa[i : i + 11, j : j + 11, ch], pb[i : i + 11, j : j + 11, ch]
                ma, mb = (w * wa).sum(), (w * wb).sum()
                va, vb = (w * wa * wa).sum() - ma**2, (w * wb * wb).sum() - mb**2
                cov = (w * wa * wb).sum() - ma * mb
                total += ((2 * ma * mb + 1e-4) * (2 * cov + 9e-4)) / ((ma**2 + mb**2 + 1e-4) * (va + vb + 9e-4))
    return total / (h * wd * c)


def test_ssim_matches_float64_reference():
    rng = np.random.default_rng(0)
    a = rng.random((13, 17, 3))
    b = np.clip(a + rng.normal(scale=0.1, size=a.shape), 0, 1)
    assert abs(ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()) - ssim_reference(a, b)) < 1e-6


def test_ssim_in_float32_is_within_5e_5_of_float64_on_a_noisy_white_background():
    """The metric runs in float32 (7x faster); near-white areas are where a float32 variance
    (E[x^2] - E[x]^2 near 1 - 1) loses most: 1.1e-5 here, under half the last digit reported."""
    gen = torch.Generator().manual_seed(0)
    a = torch.ones(200, 200, 3, dtype=torch.float64)
    a[50:150, 60:140] = torch.rand(100, 80, 3, generator=gen, dtype=torch.float64)
    b = (a + 0.05 * torch.randn(a.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    assert abs(ssim(a.float(), b.float()) - ssim(a, b)) < 5e-5


def test_ssim_map_reflect_is_kornias_training_loss_map():
    import kornia

    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 19, 23, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    ours = ssim_map(x, y, padding="reflect", eps=1e-12)
    torch.testing.assert_close(ours, kornia.metrics.ssim(x, y, 11), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(
        ssim_map(x.float(), y.float(), padding="reflect", eps=1e-12), ours.float(), rtol=1e-5, atol=1e-5
    )


@pytest.mark.parametrize("padding", ["zeros", "reflect"])
def test_ssim_map_gradcheck(padding):
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 2, 12, 13, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 2, 12, 13, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: ssim_map(a, y, padding=padding), (x,))


@pytest.mark.parametrize("padding", ["zeros", "reflect"])
def test_fast_ssim_map_equals_the_autograd_one_and_passes_gradcheck(padding):
    # the training loss's path: the same map, its hand-written gradient against autograd's
    g = torch.Generator().manual_seed(2)
    x = torch.rand(2, 3, 14, 17, generator=g, dtype=torch.float64, requires_grad=True)
    y = (x.detach() + 0.2 * torch.randn(x.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    w = torch.rand(2, 3, 14, 17, generator=g, dtype=torch.float64)
    ref = ssim_map(x, y, padding=padding, eps=1e-12)
    fast = ssim_map_fast(x, y, padding=padding, eps=1e-12)
    torch.testing.assert_close(fast, ref, rtol=0, atol=0)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    (g_fast,) = torch.autograd.grad((fast * w).sum(), x)
    torch.testing.assert_close(g_fast, g_ref, rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(lambda a: ssim_map_fast(a, y, padding=padding, eps=1e-12), (x,))


def test_ssim_map_refuses_bad_input():
    x = torch.rand(1, 3, 16, 16)
    for fn in (ssim_map, ssim_map_fast):
        with pytest.raises(ValueError, match="padding"):
            fn(x, x, padding="circular")
        with pytest.raises(ValueError, match="one shape"):
            fn(x, x[..., :8])


def write_random_lpips(folder, net="alex", seed=0):
    """torchvision-format backbone + LPIPS linear layers with random weights (positive lins)."""
    from wgs.lpips import BACKBONE_FILES, CHANNELS, LIN_FILES, _features

    g = torch.Generator().manual_seed(seed)
    feats = _features(net)
    state = {}
    for k, v in feats.state_dict().items():
        state[f"features.{k}"] = torch.randn(v.shape, generator=g) * (0.1 if k.endswith("weight") else 0.01)
    state["classifier.1.weight"] = torch.zeros(4, 4)  # torchvision files hold more than the features
    torch.save(state, folder / BACKBONE_FILES[net])
    lins = {f"lin{i}.model.1.weight": torch.rand(1, ch, 1, 1, generator=g) for i, ch in enumerate(CHANNELS[net])}
    torch.save(lins, folder / LIN_FILES[net])
    return state, lins


def lpips_by_hand(state, lins, a, b):
    """AlexNet LPIPS written out layer by layer."""
    shift = torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None]
    scale = torch.tensor([0.458, 0.448, 0.450])[None, :, None, None]

    def feats(x):
        x = (x * 2 - 1 - shift) / scale
        out = []
        x = F.relu(F.conv2d(x, state["features.0.weight"], state["features.0.bias"], stride=4, padding=2))
        out.append(x)
        x = F.max_pool2d(x, 3, 2)
        x = F.relu(F.conv2d(x, state["features.3.weight"], state["features.3.bias"], padding=2))
        out.append(x)
        x = F.max_pool2d(x, 3, 2)
        for i in (6, 8, 10):
            x = F.relu(F.conv2d(x, state[f"features.{i}.weight"], state[f"features.{i}.bias"], padding=1))
            out.append(x)
        return out

    total = 0.0
    for i, (x, y) in enumerate(zip(feats(a), feats(b), strict=True)):
        x = x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        y = y / (y.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        total = total + ((x - y) ** 2 * lins[f"lin{i}.model.1.weight"]).sum(1).mean()
    return float(total)


def test_lpips_against_hand_computed_values(tmp_path, monkeypatch):
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    state, lins = write_random_lpips(hub)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("WGS_LPIPS_WEIGHTS", raising=False)
    m = LPIPS("alex")
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(1, 3, 64, 64, generator=g), torch.rand(1, 3, 64, 64, generator=g)
    assert float(m(a, b)) == pytest.approx(lpips_by_hand(state, lins, a, b), rel=1e-5)
    assert float(m(a, a)) == 0.0


def test_lpips_vgg_loads_and_missing_weights_are_explained(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "none"))
    monkeypatch.delenv("WGS_LPIPS_WEIGHTS", raising=False)
    with pytest.raises(LpipsUnavailable, match="alexnet-owt-7be5be79.pth"):
        LPIPS("alex")
    write_random_lpips(tmp_path, "vgg")
    m = LPIPS("vgg", weights_dir=tmp_path)
    x = torch.rand(1, 3, 32, 32)
    assert float(m(x, x)) == 0.0 and float(m(x, 1 - x)) > 0


def test_lpips_linear_layers_from_an_installed_lpips_package(tmp_path, monkeypatch):
    """The backbone from the torch hub folder, the linear layers from `lpips/weights/v0.1/`."""
    from wgs.lpips import LIN_FILES

    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    write_random_lpips(hub)
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('wgs must not import lpips')\n")
    (hub / LIN_FILES["alex"]).rename(pkg / "weights" / "v0.1" / LIN_FILES["alex"])
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("WGS_LPIPS_WEIGHTS", raising=False)
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    m = LPIPS("alex")
    assert m.sources["linear"] == str(pkg / "weights" / "v0.1" / "alex.pth")
