"""The training loop's half-size schedule (`TrainConfig.half_size_until`) and `scene.dataset.halved`."""

import pytest
import torch
from conftest import ring_w2c

import wgs.gaussians.trainer as trainer
from wgs.gaussians.splats import create_splats
from wgs.gaussians.trainer import TrainConfig
from wgs.scene.dataset import Frame, halved
from wgs.shape.hull import project_points


def frame(h=7, w=9, seed=0, mask=True):
    gen = torch.Generator().manual_seed(seed)
    K = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 3.5], [0, 0, 1]])
    m = (torch.rand(h, w, generator=gen) > 0.4).float() * torch.rand(h, w, generator=gen) if mask else None
    return Frame(K, torch.eye(4), w, h, name="a.png", image=torch.rand(h, w, 3, generator=gen), mask=m)


def test_halving_commutes_with_compositing_on_a_background():
    f = frame()
    h = halved(f)
    assert (h.width, h.height) == (4, 3) and h.image.shape == (3, 4, 3) and h.mask.shape == (3, 4)
    bg = torch.tensor([0.2, 0.5, 0.9])
    full = f.image * f.mask[..., None] + bg * (1 - f.mask[..., None])
    pooled = torch.nn.functional.avg_pool2d(full.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    assert torch.allclose(h.image * h.mask[..., None] + bg * (1 - h.mask[..., None]), pooled, atol=1e-6)


def test_a_halved_frame_without_a_mask_is_its_pixels_means():
    f = frame(8, 8, mask=False)
    h = halved(f)
    assert h.mask is None
    assert torch.allclose(h.image[0, 0], f.image[:2, :2].reshape(4, 3).mean(0))


def test_a_point_lands_at_half_its_pixel_coordinates():
    """Pixel centres lie at +0.5: the 2x2 block's centre at full size is the pixel centre at half."""
    f = frame()
    point = torch.tensor([[0.13, -0.07, 2.0]])
    full, _ = project_points(point, f.viewmat, f.K)
    half, _ = project_points(point, f.viewmat, halved(f).K)
    assert torch.allclose(half, full / 2, atol=1e-6)


@pytest.fixture
def sizes(monkeypatch):
    """The (width, height) of every render the training loop asks for, in order."""
    seen = []
    real = trainer.rasterize

    def spy(*args, **kw):
        seen.append(args[7:9])
        return real(*args, **kw)

    monkeypatch.setattr(trainer, "rasterize", spy)
    return seen


@pytest.mark.parametrize("until", [0.0, 0.5, 1.0])
def test_the_early_iterations_see_the_views_at_half_size(sizes, until):
    gen = torch.Generator().manual_seed(0)
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
    disc = ((torch.arange(16)[:, None] - 7.5) ** 2 + (torch.arange(16)[None] - 7.5) ** 2 < 30).float()
    cameras = [torch.tensor(m, dtype=torch.float32) for m in ring_w2c(radius=2.0)[:2]]
    views = [
        Frame(K, w2c, 16, 16, name=f"{i}.png", image=torch.rand(16, 16, 3, generator=gen), mask=disc)
        for i, w2c in enumerate(cameras)
    ]
    splats = create_splats(
        torch.randn(60, 3, generator=gen) * 0.2, torch.rand(60, 3, generator=gen), torch.full((60,), 0.05), 0
    )
    cfg = TrainConfig(iterations=10, refine_start=100, floater_every=0, log_every=1, half_size_until=until)
    res = trainer.train_gaussians(splats, views, cfg, torch.device("cpu"), extent=1.0, seed=0)
    assert all(torch.isfinite(torch.tensor(res.losses)))
    assert sizes == [(8, 8) if it <= until * cfg.iterations else (16, 16) for it in range(1, cfg.iterations + 1)]


def test_half_size_until_is_a_fraction():
    from wgs.config import resolve
    from wgs.errors import WgsError

    with pytest.raises(WgsError, match="half_size_until"):
        resolve("coarse", None, {"coarse": {"half_size_until": 1.5}}, {})


def test_pseudo_views_follow_the_same_schedule(sizes):
    gen = torch.Generator().manual_seed(1)
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
    w2c = [torch.tensor(m, dtype=torch.float32) for m in ring_w2c(radius=2.0)[:2]]
    photo = Frame(K, w2c[0], 16, 16, name="a.png", image=torch.rand(16, 16, 3, generator=gen))
    pseudo = trainer.PseudoViews(
        [Frame(K, w2c[1], 16, 16, name="p.png", image=torch.rand(16, 16, 3, generator=gen))],
        [1.0],
        lambda it: 1.0,
        torch.ones(3),
        every=1,
    )
    splats = create_splats(
        torch.randn(60, 3, generator=gen) * 0.2, torch.rand(60, 3, generator=gen), torch.full((60,), 0.05), 0
    )
    cfg = TrainConfig(iterations=6, refine_start=100, floater_every=0, log_every=1, half_size_until=0.5)
    trainer.train_gaussians(
        splats, [photo], cfg, torch.device("cpu"), extent=1.0, seed=0, has_masks=False, pseudo=pseudo
    )
    # each iteration renders its photo, then its pseudo view
    assert sizes == [(8, 8)] * 6 + [(16, 16)] * 6


def test_the_fast_preset_trains_at_full_size_and_the_default_does_not():
    from wgs.config import resolve

    for stage in ("coarse", "mask_data", "fine"):
        assert resolve(stage, "fast", {}, {}).half_size_until == 0.0
        assert resolve(stage, None, {}, {}).half_size_until > 0.0
    assert resolve("coarse", "fast", {}, {}).member_half_size_until == 0.0


def test_the_ensembles_other_models_train_at_half_size_for_their_own_share():
    from wgs.config import resolve
    from wgs.errors import WgsError
    from wgs.stages.coarse.settings import model_config

    cfg = resolve("coarse", None, {}, {})
    assert model_config(cfg, 0) == cfg  # G_c keeps its own
    members = {model_config(cfg, i).half_size_until for i in range(1, cfg.ensemble)}
    assert members == {cfg.member_half_size_until} and cfg.member_half_size_until > cfg.half_size_until
    halved = resolve("coarse", None, {"coarse": {"member_half_size_until": 1.0}}, {})
    assert {model_config(halved, i).half_size_until for i in range(1, halved.ensemble)} == {1.0}
    with pytest.raises(WgsError, match="member_half_size_until"):
        resolve("coarse", None, {"coarse": {"member_half_size_until": 1.5}}, {})
