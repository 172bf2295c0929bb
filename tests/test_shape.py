"""The hull grid, its silhouettes (numba against the torch reference), silhouette scores, the
leave-one-out estimate, and carving: fat parts go, thin parts and real masks' pixels stay."""

import math

import pytest
import torch

from wgs.scene.camera import Camera
from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at
from wgs.shape.carve import CarveParams, carve
from wgs.shape.hull import (
    OFF_FRAME,
    HullGrid,
    grid_centres,
    hull_votes,
    hull_votes_torch,
    mask_lookup,
    silhouette,
    silhouette_torch,
    visual_hull_grid,
    votes_needed,
)
from wgs.shape.scores import leave_one_out, mean_scores, silhouette_scores

SIZE, FOCAL = 96, 120.0


def camera(azimuth_deg: float, elevation_deg: float, distance: float = 2.0) -> Camera:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = torch.tensor([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)]).double().numpy() * distance
    up = [0, 1.0, 0] if abs(elevation_deg) > 80 else [0, 0, 1.0]
    w2c = torch.tensor(look_at(eye, eye * 0, torch.tensor(up).double().numpy()), dtype=torch.float32)
    K = torch.tensor([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]])
    return Camera(K, w2c, SIZE, SIZE)


def mug(p: torch.Tensor) -> torch.Tensor:
    """A cylinder (radius 0.3, |z| < 0.3) with a thin handle (a 0.04-thick rectangular loop) at +x."""
    r = p[:, :2].norm(dim=-1)
    body = (r < 0.3) & (p[:, 2].abs() < 0.3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    loop = (x > 0.28) & (x < 0.5) & (y.abs() < 0.04) & (z.abs() < 0.2)
    hole = (x > 0.28) & (x < 0.46) & (z.abs() < 0.16)
    return body | (loop & ~hole)


def true_mask(inside, cam: Camera, box: float = 0.7) -> torch.Tensor:
    """[H, W] bool: rays of `cam` that meet the shape `inside` (marched on a fine grid of the box)."""
    grid = HullGrid(torch.full((3,), -box), torch.full((3,), box), torch.ones(200, 200, 200, dtype=torch.bool))
    occ = inside(grid.centres()).reshape(200, 200, 200)
    return silhouette(grid.with_occupancy(occ), cam)[0]


def frames_of(inside, cams) -> list[Frame]:
    return [
        Frame(
            c.K,
            c.viewmat,
            c.width,
            c.height,
            name=f"v{i}.png",
            image=torch.rand(SIZE, SIZE, 3),
            mask=true_mask(inside, c).float(),
        )
        for i, c in enumerate(cams)
    ]


@pytest.fixture(scope="module")
def mug_hull():
    side = frames_of(mug, [camera(a, 0.0) for a in (0, 90, 180, 270)])
    grid = visual_hull_grid(side, resolution=64, extent=0.7, tolerate=0)
    return side, grid


def test_silhouette_fast_path_matches_reference(mug_hull):
    _, grid = mug_hull
    for cam in (camera(30, 50), camera(200, -70), camera(0, 90)):
        fast, d_fast = silhouette(grid, cam)
        ref, d_ref = silhouette_torch(grid, cam)
        assert (fast != ref).sum() <= 2  # float64 against float32 samples at voxel faces
        both = fast & ref
        assert torch.allclose(d_fast[both], d_ref[both], atol=0.02)
        assert fast.sum() > 100


@pytest.mark.parametrize("off_frame", OFF_FRAME)
@pytest.mark.parametrize("tolerate", [0, 1, 3])
def test_hull_votes_fast_path_matches_reference(mug_hull, tolerate, off_frame):
    side, _ = mug_hull
    c = side[3]  # a view of another size: the kernel reads every mask from one packed buffer
    crop = torch.tensor([[2.0], [2.0], [1.0]])  # ... and a close-up that crops the mug
    frames = side[:2] + [
        Frame(
            side[2].K * crop,
            side[2].viewmat,
            SIZE,
            SIZE,
            name="close.png",
            mask=true_mask(mug, Camera(side[2].K * crop, side[2].viewmat, SIZE, SIZE)).float(),
        ),
        Frame(
            c.K * torch.tensor([[0.5], [0.5], [1.0]]),
            c.viewmat,
            SIZE // 2,
            SIZE // 2,
            name="half.png",
            mask=(torch.rand(SIZE // 2, SIZE // 2) > 0.5).float(),
        ),
    ]
    points = torch.rand(20000, 3) * 1.6 - 0.8
    fast = hull_votes(frames, points, tolerate, off_frame=off_frame)
    ref = hull_votes_torch(frames, points, tolerate, off_frame=off_frame)
    assert fast.dtype == torch.int32 and fast.shape == (20000,)
    assert torch.equal(fast, ref)
    need = votes_needed(len(frames), tolerate, off_frame)
    assert 0 < int((ref >= need).sum()) < 20000


def test_a_photo_abstains_only_where_the_object_runs_out_of_it():
    """Outside the frame, a photo abstains where its mask reaches the nearest border pixel and says
    background where it does not; in the frame it says what its mask says; behind it, background."""
    cam = camera(0, 0)
    mask = torch.zeros(SIZE, SIZE)
    mask[40:60, : SIZE // 2] = 1.0  # runs out of the left edge only
    w2c = cam.viewmat

    def at(u, v, depth=2.0):  # the world point at pixel (u, v) and camera depth
        p_cam = torch.linalg.inv(cam.K) @ torch.tensor([u, v, 1.0]) * depth
        return ((p_cam - w2c[:3, 3]) @ w2c[:3, :3])[None]

    cases = {
        (-20.0, 50.0): (False, True),  # off the left edge, beside the mask: abstain
        (-20.0, 10.0): (False, False),  # off the left edge, beside background: background
        (SIZE + 20.0, 50.0): (False, False),  # off the right edge: background
        (20.0, 50.0): (True, False),
        (70.0, 50.0): (False, False),
    }
    for (u, v), expected in cases.items():
        holds, abstains = mask_lookup(cam, mask, at(u, v))
        assert (bool(holds), bool(abstains)) == expected, (u, v)
    assert not mask_lookup(cam, mask, at(-20.0, 50.0, depth=-1.0))[1].any()  # behind the camera
    assert mask_lookup(cam, mask, at(-20.0, 50.0), off_frame="object")[0].all()
    assert not mask_lookup(cam, mask, at(-20.0, 50.0), off_frame="background")[0].any()


def test_hull_silhouette_is_the_mask_at_training_cameras_and_holds_the_object_elsewhere():
    sphere = lambda p: p.norm(dim=-1) < 0.3  # noqa: E731
    frames = frames_of(sphere, [camera(a, e) for a, e in ((0, 0), (90, 10), (180, -10), (270, 0), (45, 80))])
    grid = visual_hull_grid(frames, resolution=64, extent=0.7, tolerate=0)
    for f in frames:
        assert silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5)["iou"] > 0.95
    for cam in (camera(45, 30), camera(135, -40)):
        s = silhouette_scores(silhouette(grid, cam)[0], true_mask(sphere, cam))
        assert s["missed"] < 0.02 and 0.0 < s["excess"] < 0.3


def test_hull_keeps_parts_thinner_than_its_first_pass_cells():
    """The first pass (32³ over the extent) only finds the hull's box; a thin part that none of its
    cell centres falls in must still be inside the box the second pass carves."""

    def lollipop(p):  # a ball of radius 0.12 and a 0.04-thick stick to x = 0.45
        stick = (p[:, 0] > 0.0) & (p[:, 0] < 0.45) & (p[:, 1].abs() < 0.02) & (p[:, 2].abs() < 0.02)
        return (p.norm(dim=-1) < 0.12) | stick

    frames = frames_of(lollipop, [camera(a, e, distance=1.5) for a, e in ((30, 20), (120, 10), (210, 25), (300, 15))])
    grid = visual_hull_grid(frames, resolution=64, extent=1.0, tolerate=0)
    assert grid.hi[0] > 0.45
    for f in frames:
        assert silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5)["missed"] < 0.01


def test_a_kept_hull_is_the_same_hull_and_a_copy(mug_hull):
    side, grid = mug_hull
    again = visual_hull_grid(side, resolution=64, extent=0.7, tolerate=0)
    assert torch.equal(again.occ, grid.occ) and torch.equal(again.lo, grid.lo)
    again.occ.zero_()
    third = visual_hull_grid(side, resolution=64, extent=0.7, tolerate=0)
    assert torch.equal(third.occ, grid.occ)  # the caller's change stays its own
    cut = [Frame(f.K, f.viewmat, f.width, f.height, name=f.name, image=f.image, mask=f.mask.clone()) for f in side]
    cut[0].mask[:, : SIZE // 2] = 0.0  # another mask is another hull
    assert visual_hull_grid(cut, resolution=64, extent=0.7, tolerate=0).occ.sum() < grid.occ.sum()


def test_silhouette_scores_exact():
    true = torch.zeros(4, 4, dtype=torch.bool)
    true[:2, :2] = True  # 4 px
    pred = torch.zeros(4, 4, dtype=torch.bool)
    pred[:2, :3] = True  # 6 px, 4 shared
    s = silhouette_scores(pred, true)
    assert s == {"iou": 4 / 6, "excess": 2 / 4, "missed": 0.0}
    assert silhouette_scores(pred & False, true & False)["iou"] == 1.0
    assert mean_scores({}) is None
    assert mean_scores({"a": s, "b": {"iou": 0.0, "excess": 0.0, "missed": 1.0}})["iou"] == pytest.approx(1 / 3)


def test_leave_one_out_sees_a_fatter_hull_with_fewer_views():
    sphere = lambda p: p.norm(dim=-1) < 0.3  # noqa: E731
    ring = frames_of(sphere, [camera(a, 0.0) for a in (0, 90, 180, 270)])
    loo = leave_one_out(ring, resolution=48, extent=0.7)
    assert set(loo) == {f.name for f in ring}
    # each left-out side view sees the others' hull: the two views at 90 degrees to it bound it
    # exactly, so it fits there; from the ring of 8 it fits as well
    assert all(s["missed"] < 0.05 for s in loo.values())
    top = frames_of(sphere, [camera(0, 0.0), camera(90, 0.0), camera(0, 89.0)])
    loo_top = leave_one_out(top, resolution=48, extent=0.7)
    # without the top view the others' hull is a square prism from above: 4/pi the disc's area
    assert loo_top["v2.png"]["excess"] > 0.15 and loo_top["v2.png"]["iou"] < 0.9


def test_carving_fat_hull_toward_truth_keeps_thin_handle(mug_hull):
    side, grid = mug_hull
    top, bottom = camera(10, 89.0), camera(10, -89.0)
    before = [silhouette_scores(silhouette(grid, c)[0], true_mask(mug, c))["iou"] for c in (top, bottom)]
    pseudo = [camera(a, e) for a in range(0, 360, 45) for e in (-60.0, 60.0)]
    oracle = [true_mask(mug, c).float() for c in pseudo]  # predictions that are right
    # a voxel is outside when one view's true silhouette leaves it out: no fraction of the views is asked
    carved, counts = carve(
        grid, pseudo, oracle, side, CarveParams(min_views=2, min_fraction=0.0, max_carve=1.0, dilate_px=1)
    )
    after = [silhouette_scores(silhouette(carved, c)[0], true_mask(mug, c))["iou"] for c in (top, bottom)]
    assert counts["carved"] > 0
    assert all(a > b + 0.08 for a, b in zip(after, before, strict=True)) and min(after) > 0.88, (before, after)
    # the handle's voxels in the hull survive
    centres = grid.centres()
    handle = mug(centres) & (centres[:, 0] > 0.31) & grid.occ.reshape(-1)
    kept = carved.occ.reshape(-1)[handle].float().mean()
    assert handle.sum() > 20 and kept > 0.9


def test_carving_never_uncovers_a_real_mask_pixel(mug_hull):
    side, grid = mug_hull
    gen = torch.Generator().manual_seed(0)
    pseudo = [camera(a, e) for a, e in ((0, 30), (100, -20), (220, 45), (300, 0))]
    for trial in range(3):  # predictions that are wrong on purpose: random blobs of "background"
        wrong = [
            (torch.rand(SIZE // 8, SIZE // 8, generator=gen) > 0.3)
            .float()
            .repeat_interleave(8, 0)
            .repeat_interleave(8, 1)
            for _ in pseudo
        ]
        carved, counts = carve(
            grid, pseudo, wrong, side, CarveParams(min_views=1, min_fraction=0.1, max_carve=1.0, dilate_px=0)
        )
        assert counts["carved"] > 0
        for f in side:
            was = silhouette(grid, f)[0] & (f.mask > 0.5)
            assert not (was & ~silhouette(carved, f)[0]).any(), trial
    assert counts["restored"] > 0


def test_carving_bounded_per_call(mug_hull):
    side, grid = mug_hull
    pseudo = [camera(a, 60.0) for a in (0, 120, 240)]
    nothing = [torch.zeros(SIZE, SIZE) for _ in pseudo]
    carved, counts = carve(grid, pseudo, nothing, [], CarveParams(max_carve=0.1, min_views=1))
    assert counts["carved"] == int(0.1 * counts["voxels"])
    assert int(carved.occ.sum()) == counts["voxels"] - counts["carved"]


def test_grid_centres_and_index_agree():
    lo, hi = torch.tensor([-1.0, 0.0, 2.0]), torch.tensor([1.0, 1.0, 3.0])
    grid = HullGrid(lo, hi, torch.zeros(5, 5, 5, dtype=torch.bool))
    c = grid_centres(lo, hi, 5)
    assert torch.equal(grid.voxel_index(c), torch.arange(125))
    assert grid.voxel_index(torch.tensor([[5.0, 0.5, 2.5]])).item() == -1


def test_silhouette_net_tiny_config_runs_at_any_size():
    from wgs.models.silhouette_net import SilhouetteNet, SilhouetteNetConfig
    from wgs.shape.features import predict_object

    for levels in (2, 4):
        net = SilhouetteNet(SilhouetteNetConfig(channels=8, levels=levels, work_size=40))
        assert net(torch.rand(2, 6, 37, 50)).shape == (2, 1, 37, 50)
        seen = []
        net.register_forward_hook(lambda m, args, out, seen=seen: seen.append(args[0].shape[-2:]))
        prob = predict_object(net, torch.rand(6, 200, 150))  # run at the working size, resized back
        assert seen == [(40, 30)] and prob.shape == (200, 150) and ((prob >= 0) & (prob <= 1)).all()


def test_hull_channels_depth_is_centred(mug_hull):
    from wgs.shape.features import hull_channels

    _, grid = mug_hull
    hull, depth = hull_channels(grid, camera(30, 20))
    assert set(hull.unique().tolist()) == {0.0, 1.0} and (depth[hull == 0] == 0).all()
    # first hits lie within half the box's diagonal of its centre, most of them before it
    front = depth[hull == 1]
    assert (front.abs() <= 1).all() and front.median() < 0


def test_volume_net_tiny_config_gives_a_probability_per_occupied_voxel(mug_hull):
    from wgs.models.volume_net import VolumeNet, VolumeNetConfig
    from wgs.shape.volume import occupied_probability

    side, grid = mug_hull
    for levels in (1, 2):
        net = VolumeNet(VolumeNetConfig(channels=8, levels=levels, resolution=16)).eval()
        assert net(torch.rand(2, 4, 16, 16, 16)).shape == (2, 1, 16, 16, 16)
        prob = occupied_probability(net, side, grid)
        assert prob.shape == (int(grid.occ.sum()),) and ((prob >= 0) & (prob <= 1)).all()


def test_volume_inputs_hold_the_strict_hull_and_do_not_depend_on_image_size(mug_hull):
    from wgs.shape.hull import mask_votes
    from wgs.shape.volume import cube_around, volume_inputs

    side, grid = mug_hull
    box = cube_around(grid, 24)
    x = volume_inputs(side, box)
    votes, _ = mask_votes(side, box.centres())
    assert torch.equal(x[0].reshape(-1) > 0.5, votes == len(side))
    assert ((x[1] > 0) == (x[0] > 0.5)).all() and (x[2] >= x[1]).all() and (x[3] == len(side) / 8).all()
    # the same views at twice the pixels: the scaled mask distances agree to about a pixel
    big = [
        Frame(
            torch.diag(torch.tensor([2.0, 2.0, 1.0])) @ f.K,
            f.viewmat,
            2 * SIZE,
            2 * SIZE,
            name=f.name,
            mask=f.mask.repeat_interleave(2, 0).repeat_interleave(2, 1),
        )
        for f in side
    ]
    x2 = volume_inputs(big, box)
    inside = x[0] > 0.5
    assert (x2[1] - x[1])[inside].abs().median() < 0.03


def test_volume_target_is_inside_the_few_view_hull(mug_hull):
    from wgs.shape.volume import cube_around, volume_inputs, volume_target

    side, grid = mug_hull
    more = side + frames_of(mug, [camera(10, 89.0), camera(10, -89.0), camera(45, 45.0)])
    box = cube_around(grid, 24)
    hull, target = volume_inputs(side, box)[0] > 0.5, volume_target(more, box) > 0.5
    assert not (target & ~hull).any() and target.sum() < 0.97 * hull.sum()  # the new views cut some corners


def test_volume_carving_toward_truth_keeps_the_handle_and_the_real_masks(mug_hull):
    from wgs.shape.carve import carve_volume

    side, grid = mug_hull
    centres = grid.centres()[grid.occ.reshape(-1)]
    truth = mug(centres).float()  # a V that is right
    carved, counts = carve_volume(grid, truth, side, CarveParams(max_carve=1.0))
    top, bottom = camera(10, 89.0), camera(10, -89.0)
    for c in (top, bottom):
        before = silhouette_scores(silhouette(grid, c)[0], true_mask(mug, c))["iou"]
        after = silhouette_scores(silhouette(carved, c)[0], true_mask(mug, c))["iou"]
        assert after > before + 0.08 and after > 0.88, (before, after)
    handle = mug(centres) & (centres[:, 0] > 0.31)
    assert handle.sum() > 20 and carved.occ.reshape(-1)[grid.occ.reshape(-1)][handle].all()
    gen = torch.Generator().manual_seed(1)
    wrong, counts = carve_volume(
        grid, torch.rand(centres.shape[0], generator=gen), side, CarveParams(max_carve=1.0, volume_empty_below=0.5)
    )
    assert counts["carved"] > 0 and counts["restored"] > 0
    for f in side:
        was = silhouette(grid, f)[0] & (f.mask > 0.5)
        assert not (was & ~silhouette(wrong, f)[0]).any()


def test_volume_augment_turns_inputs_and_target_alike():
    from tools.prior.train_volume import augment

    gen = torch.Generator().manual_seed(0)
    x = torch.rand(3, 4, 8, 8, 8)
    for _ in range(6):
        xa, ya = augment(x, x[:, 0].clone(), gen)
        assert torch.equal(xa[:, 0], ya) and sorted(xa.flatten().tolist()) == sorted(x.flatten().tolist())


def test_a_volume_model_that_hurts_the_leave_one_out_silhouettes_is_left_out(monkeypatch):
    import wgs.shape.carve as carving

    views = frames_of(mug, [camera(a, e) for a, e in ((0, 0), (100, 10), (210, -10), (300, 40))])
    grid = visual_hull_grid(views, resolution=48, extent=0.7, tolerate=0)
    for cuts_half in (True, False):  # a V that calls the half y > 0 background / one that keeps everything

        def prob(model, frames, g, cuts_half=cuts_half):
            pts = g.centres()[g.occ.reshape(-1)]
            return torch.where((pts[:, 1] > 0) & cuts_half, 0.0, 1.0)

        monkeypatch.setattr(carving, "occupied_probability", prob)
        params = CarveParams(max_carve=1.0, volume_check_margin=0.0)
        carved, record = carving.carve_with_volume(None, views, grid, params, resolution=48)
        assert record["used"] is not cuts_half, record
        assert torch.equal(carved.occ, grid.occ)  # vetoed, or nothing to carve
        if cuts_half:  # the real masks' rule keeps most of it: the held-out views see what is left
            assert record["leave_one_out_iou_carved"] < record["leave_one_out_iou"]
