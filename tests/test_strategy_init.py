"""Densification strategy, visual hull, kNN scales, floaters."""

import math

import torch

from wgs.gaussians.init import floater_mask, knn_mean_distance, knn_mean_distance_torch, visual_hull
from wgs.gaussians.splats import create_splats
from wgs.gaussians.strategy import DensifyStrategy, remove, reset_opacity, split
from wgs.gaussians.trainer import TrainConfig, make_optimizers
from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at


def params_and_opts(n=20):
    sp = create_splats(torch.randn(n, 3), torch.rand(n, 3), torch.full((n,), 0.05), 1)
    params = {k: v.requires_grad_(True) for k, v in sp.items()}
    opts = make_optimizers(params, TrainConfig(), 1.0)
    # take one step so the Adam state exists
    sum(p.sum() for p in params.values()).backward()
    for o in opts.values():
        o.step()
    return params, opts


def assert_consistent(params, opts):
    n = params["means"].shape[0]
    for k, p in params.items():
        assert p.shape[0] == n
        opt = opts[k]
        assert opt.param_groups[0]["params"][0] is p
        assert opt.state[p]["exp_avg"].shape == p.shape


def test_remove_split_reset_keep_adam_state_aligned():
    params, opts = params_and_opts()
    mask = torch.zeros(20, dtype=torch.bool)
    mask[:5] = True
    remove(params, opts, mask)
    assert params["means"].shape[0] == 15
    assert_consistent(params, opts)
    m2 = torch.zeros(15, dtype=torch.bool)
    m2[:3] = True
    old_scale = torch.exp(params["scales"][:3]).clone()
    split(params, opts, m2)
    assert params["means"].shape[0] == 15 - 3 + 6
    torch.testing.assert_close(torch.exp(params["scales"][-6:-3]), old_scale / 1.6)
    assert_consistent(params, opts)
    reset_opacity(params, opts, 0.01)
    assert torch.sigmoid(params["opacities"]).max() <= 0.01 + 1e-6


def test_strategy_grows_high_gradient_and_respects_cap():
    params, opts = params_and_opts()
    strat = DensifyStrategy(
        refine_start=0, refine_every=1, max_gaussians=24, grad_threshold=1e-3, reset_every=0, prune_opacity=0.0
    )
    state = strat.initial_state()
    means2d = torch.zeros(20, 2, requires_grad=True)
    means2d.grad = torch.zeros(20, 2)
    means2d.grad[:10] = 1.0  # ten with a high gradient
    strat.accumulate(state, {"means2d": means2d, "visible": torch.ones(20, dtype=torch.bool), "width": 8, "height": 8})
    out = strat.step(params, opts, state, 1)
    assert out["cloned"] + out["split"] > 0
    assert params["means"].shape[0] <= 24
    assert_consistent(params, opts)


def test_strategy_reads_gsplats_batched_means2d_like_ours():
    # gsplat's CUDA path hands over means2d as [1, N, 2] (meta["means2d_batched"]); ours is [N, 2]
    g = torch.Generator().manual_seed(0)
    grad = torch.randn(20, 2, generator=g)
    visible = torch.rand(20, generator=g) > 0.3
    states = []
    for batched in (False, True):
        means2d = torch.zeros(1, 20, 2) if batched else torch.zeros(20, 2)
        means2d.requires_grad_(True)
        means2d.grad = grad[None].clone() if batched else grad.clone()
        strat = DensifyStrategy()
        state = strat.initial_state()
        meta = {"means2d": means2d, "visible": visible, "width": 64, "height": 32}
        if batched:
            meta["means2d_batched"] = True
        strat.accumulate(state, meta)
        strat.accumulate(state, meta)
        states.append(state)
    for k in ("grad2d", "count"):
        assert states[0][k].shape == (20,)
        torch.testing.assert_close(states[1][k], states[0][k])
    scaled = grad * torch.tensor([32.0, 16.0])
    torch.testing.assert_close(states[0]["grad2d"], torch.where(visible, 2 * scaled.norm(dim=-1), 0.0))


def sphere_frames(radius=0.3, size=48, n=4):
    frames = []
    f = 60.0
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = torch.tensor([math.cos(a), math.sin(a), 0.4]).double().numpy() * 1.0
        w2c = torch.tensor(look_at(eye, eye * 0, torch.tensor([0, 0, 1.0]).double().numpy()), dtype=torch.float32)
        ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
        # analytic silhouette of a sphere: the disc of angular radius asin(r / d)
        d = float(torch.tensor(eye).norm())
        rays = torch.stack([(xs - size / 2) / f, (ys - size / 2) / f, torch.ones_like(xs)], -1)
        rays = rays / rays.norm(dim=-1, keepdim=True)
        mask = (rays[..., 2] >= math.cos(math.asin(radius / d))).float()
        frames.append(Frame(K, w2c, size, size, name=f"v{i}.png", image=torch.rand(size, size, 3), mask=mask))
    return frames


def test_visual_hull_of_sphere_lies_inside_its_hull_bound():
    frames = sphere_frames()
    pts, cols = visual_hull(frames, resolution=48, extent=0.6, max_points=100000)
    r = pts.norm(dim=1)
    assert pts.shape[0] > 100 and cols.shape == pts.shape
    # the hull of 4 views contains the sphere; its surface voxels lie between the sphere and the
    # 4-view hull bound (at most r / cos(45°) in the plane of the cameras), plus a voxel of slack
    voxel = 2 * 0.6 / 48 * math.sqrt(3)
    pixel = 1.4 / 60.0  # mask quantisation: about one pixel footprint at the object
    assert r.min() > 0.3 - voxel - pixel
    assert r.max() < 0.3 / math.cos(math.pi / 4) * 1.15 + voxel


def test_hull_points_take_the_mean_colour_of_the_views_whose_masks_hold_them():
    frames = sphere_frames()
    gen = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    for f in frames:
        f.image = torch.full_like(f.image, 0.3)
    pts, cols = visual_hull(frames, resolution=32, extent=0.6, max_points=300, generator=gen())
    assert pts.shape == (300, 3)
    torch.testing.assert_close(cols, torch.full_like(cols, 0.3))
    for i, f in enumerate(frames):  # view i all one grey, i / 10: a mean of some of them
        f.image = torch.full_like(f.image, i / 10)
    again, cols = visual_hull(frames, resolution=32, extent=0.6, max_points=300, generator=gen())
    assert torch.equal(again, pts) and cols.min() >= 0.0 and cols.max() <= 0.3 + 1e-6 and cols.std() > 0


def test_empty_hull_is_a_clear_error():
    frames = sphere_frames()
    for f in frames:
        f.mask = torch.zeros_like(f.mask)
    import pytest

    from wgs.errors import InputError

    with pytest.raises(InputError, match="visual hull"):
        visual_hull(frames, resolution=16)


def test_knn_and_floaters():
    pts = torch.randn(500, 3) * 0.1
    pts[0] = torch.tensor([5.0, 5.0, 5.0])
    d = knn_mean_distance(pts, 3)
    assert d.shape == (500,) and d[0] > 10 * d[1:].median()
    # the KD-tree matches the brute-force reference
    torch.testing.assert_close(d, knn_mean_distance_torch(pts, 3, chunk=64), rtol=1e-5, atol=1e-7)
    m = floater_mask(pts, 8, 3.0)
    assert m[0] and m.sum() < 10


def test_knn_edge_cases():
    assert knn_mean_distance(torch.zeros(0, 3)).shape == (0,)
    assert knn_mean_distance(torch.zeros(1, 3)).shape == (1,)
    two = knn_mean_distance(torch.tensor([[0.0, 0, 0], [0.3, 0.4, 0]]), 3)  # k capped at n - 1
    torch.testing.assert_close(two, torch.tensor([0.5, 0.5]))
    same = knn_mean_distance(torch.ones(5, 3), 2)  # duplicates: zero distance, no NaN
    assert torch.equal(same, torch.zeros(5))


def test_strategy_fires_when_a_time_budget_jumps_past_the_interval():
    params, opts = params_and_opts()
    strat = DensifyStrategy(refine_start=0, refine_every=100, grad_threshold=1e-3, reset_every=0, prune_opacity=0.0)
    state = strat.initial_state()
    means2d = torch.zeros(20, 2, requires_grad=True)
    means2d.grad = torch.ones(20, 2)
    meta = {"means2d": means2d, "visible": torch.ones(20, dtype=torch.bool), "width": 8, "height": 8}
    strat.accumulate(state, meta)
    assert strat.step(params, opts, state, 150, prev_it=120) == {"cloned": 0, "split": 0, "pruned": 0}
    out = strat.step(params, opts, state, 250, prev_it=150)  # jumped over 200
    assert out["cloned"] + out["split"] == 20


def test_time_budget_stops_training_and_drives_the_schedule():
    import time

    from wgs.gaussians.trainer import TrainConfig, train_gaussians

    f = sphere_frames(size=16, n=2)
    sp = create_splats(torch.randn(100, 3) * 0.1, torch.rand(100, 3), torch.full((100,), 0.05), 0)
    cfg = TrainConfig(iterations=10**6, max_seconds=1.5, refine_start=10, refine_stop=10**6, floater_every=0)
    t0 = time.perf_counter()
    res = train_gaussians(sp, f, cfg, torch.device("cpu"), extent=1.0)
    assert time.perf_counter() - t0 < 10 and res.iterations < 10**6


def test_densification_defaults_live_in_one_place():
    """The training configs inherit the strategy's fields: one default per field, and
    strategy_from reads every one of them (a renamed field is an AttributeError, not a silent default)."""
    import dataclasses

    from wgs.gaussians.strategy import DensifyParams
    from wgs.gaussians.trainer import TrainConfig, strategy_from
    from wgs.stages.coarse.settings import CoarseConfig

    assert issubclass(TrainConfig, DensifyParams)
    cfg = CoarseConfig(refine_stop=123, max_gaussians=77)
    s = strategy_from(cfg, 2.0)
    assert (s.refine_stop, s.max_gaussians, s.scene_extent) == (123, 77, 2.0)
    for f in dataclasses.fields(DensifyParams):
        assert getattr(s, f.name) == getattr(cfg, f.name)
