"""Random region masks: coverage, drift, per-view differences."""

import pytest
import torch

from wgs.masking import edge_share, make_region_masks


def random_shapes(v=3, h=64, w=80, seed=0):
    """Blobby random object masks: unions of random discs."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    out = torch.zeros(v, h, w)
    for i in range(v):
        for _ in range(4):
            cx, cy = torch.rand(2, generator=g) * torch.tensor([w * 0.6, h * 0.6]) + torch.tensor([w * 0.2, h * 0.2])
            r = float(torch.rand(1, generator=g)) * 12 + 6
            out[i] = torch.maximum(out[i], (((xs - cx) ** 2 + (ys - cy) ** 2) <= r * r).float())
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("offline", [False, True])
def test_union_covers_half_the_object(seed, offline):
    obj = random_shapes(seed=seed)
    rm = make_region_masks(obj, n_regions=10, coverage=0.5, offline=offline, seed=seed)
    for v in range(obj.shape[0]):
        for it in (0, 37, 250, 999):
            hid = rm.hidden(v, it)
            cov = float((hid * obj[v]).sum() / obj[v].sum())
            assert 0.45 <= cov <= 0.55, (v, it, cov)


def test_regions_drift_online_and_stay_offline():
    obj = random_shapes()
    online = make_region_masks(obj, drift=0.1, period=100, offline=False, seed=0)
    offline = make_region_masks(obj, drift=0.1, period=100, offline=True, seed=0)
    assert not torch.equal(online.hidden(0, 0), online.hidden(0, 25))
    assert not torch.allclose(online.positions(0, 0), online.positions(0, 25))
    assert torch.equal(offline.hidden(0, 0), offline.hidden(0, 25))


def test_masks_differ_across_views():
    obj = random_shapes()
    obj[:] = obj[0]  # same object silhouette in every view
    rm = make_region_masks(obj, seed=0)
    assert not torch.equal(rm.hidden(0, 0), rm.hidden(1, 0))


def test_bad_arguments():
    obj = random_shapes()
    with pytest.raises(ValueError, match="coverage"):
        make_region_masks(obj, coverage=1.5)
    with pytest.raises(ValueError, match="empty"):
        make_region_masks(torch.zeros(1, 8, 8))


def test_edge_share_counts_the_object_on_the_frames_edge():
    mask = torch.zeros(20, 30)
    mask[5:15, 10:20] = 1.0
    assert edge_share(mask) == 0.0  # held whole
    mask[4:14, 0:12] = 1.0  # now reaching the left edge over 10 of its 18 inner rows
    assert edge_share(mask) == pytest.approx(10 / (2 * 30 + 2 * 18))
