"""Mirror views (wgs.shape.symmetry, wgs.scene.mirror): the reflection, the plane search's fast path
against the torch reference, the plane of a symmetric object, the mirrored camera, and the gate."""

import math

import pytest
import torch
from test_shape import camera, frames_of, true_mask

from wgs.scene.mirror import MirrorPlane, mirror_frame, reflect
from wgs.shape.hull import project_points, silhouette, visual_hull_grid
from wgs.shape.scores import silhouette_scores
from wgs.shape.symmetry import RayVoxels, hemisphere_directions, mirror_carve, mirror_check, mirrored_occupancy

TRUE_NORMAL = torch.tensor([0.0, 1.0, 0.0])


def duck(p: torch.Tensor) -> torch.Tensor:
    """Mirror-symmetric across y = 0 only: an ellipsoid body, a head up front at +x, a tail up at -x."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    body = (x / 0.4) ** 2 + (y / 0.22) ** 2 + (z / 0.18) ** 2 < 1
    head = (x - 0.32) ** 2 + y**2 + (z - 0.25) ** 2 < 0.12**2
    tail = (x > -0.5) & (x < -0.3) & (y.abs() < 0.05) & (z > 0.0) & (z < 0.22)
    return body | head | tail


@pytest.fixture(scope="module")
def duck_views():
    """4 photos from above the table at uneven azimuths, none on the mirror plane."""
    return frames_of(duck, [camera(a, e) for a, e in ((20, 20), (105, 35), (200, 15), (290, 30))])


def test_reflect_is_an_involution_that_keeps_the_plane():
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=torch.float64), dim=-1)
    offsets = torch.randn(4, generator=gen, dtype=torch.float64)
    once = reflect(points, normals, offsets)
    assert once.shape == (4, 50, 3)
    for b in range(4):
        twice = reflect(once[b], normals[b : b + 1], offsets[b : b + 1])[0]
        assert torch.allclose(twice, points, atol=1e-12)
        side = points @ normals[b] - offsets[b]
        assert torch.allclose(once[b] @ normals[b] - offsets[b], -side, atol=1e-12)  # the other side, as far
        on_plane = points - side[:, None] * normals[b]
        assert torch.allclose(reflect(on_plane, normals[b : b + 1], offsets[b : b + 1])[0], on_plane, atol=1e-12)


def test_hemisphere_directions_are_unit_and_spread():
    d = hemisphere_directions(200)
    assert d.shape == (200, 3) and torch.allclose(d.norm(dim=-1), torch.ones(200), atol=1e-6)
    assert (d[:, 2] > 0).all()
    # every direction of the hemisphere lies within 12 degrees of one of them
    probe = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    probe[:, 2] = probe[:, 2].abs()
    assert math.degrees(float(torch.arccos((probe @ d.T).max(-1).values.clamp(max=1)).max())) < 12


def test_mirror_fast_path_matches_reference(duck_views):
    others, left_out = duck_views[1:], duck_views[0]
    grid = visual_hull_grid(others, resolution=40, extent=0.7, tolerate=0)
    rays = RayVoxels(grid, left_out, stride=2)
    normals = torch.cat([TRUE_NORMAL[None], hemisphere_directions(30)])
    offsets = torch.linspace(-0.1, 0.1, 31)
    fast = rays.mirrored_iou(normals, offsets)
    reference = rays.iou(mirrored_occupancy(grid, normals, offsets))
    assert torch.allclose(fast, reference, atol=1e-6)
    # the reference IoU of the whole grid is the ray-marched silhouette's (at every other pixel)
    whole = rays.iou(grid.occ.reshape(1, -1))[0]
    marched = silhouette_scores(silhouette(grid, left_out)[0][::2, ::2], left_out.mask[::2, ::2] > 0.5)["iou"]
    assert float(whole) == pytest.approx(marched, abs=1e-6)


def test_the_mirror_of_a_symmetric_object_is_found_and_its_views_carve_toward_the_truth(duck_views):
    record = mirror_check(duck_views, min_gain=0.02, max_missed=0.02, directions=150)
    plane = MirrorPlane.from_json(record["plane"])
    angle = math.degrees(math.acos(min(1.0, abs(float(plane.normal @ TRUE_NORMAL)))))
    assert angle < 3 and abs(plane.offset) < 0.02, (record, angle)
    assert record["used"] and record["leave_one_out_iou_mirrored"] > record["leave_one_out_iou"] + 0.05
    grid = visual_hull_grid(duck_views, resolution=64, extent=0.7, tolerate=0)
    both = visual_hull_grid(
        duck_views + [mirror_frame(f, plane) for f in duck_views], resolution=64, extent=0.7, tolerate=0
    )
    unseen = [camera(a, e) for a, e in ((150, -60), (330, -40), (60, 80), (240, 5))]
    iou = lambda g: sum(silhouette_scores(silhouette(g, c)[0], true_mask(duck, c))["iou"] for c in unseen) / 4  # noqa: E731
    assert iou(both) > iou(grid) + 0.02, (iou(grid), iou(both))
    # the hull of the photos and their mirror images is the photos' hull cut by its own reflection
    cut, resampled = mirror_carve(grid, plane).occ.reshape(-1), sample_on(both, grid)
    assert float((cut & resampled).sum() / (cut | resampled).sum()) > 0.9
    inside = duck(both.centres()) & both.occ.reshape(-1)
    assert inside.sum() > 0.9 * duck(both.centres()).sum()  # the object itself stays


def sample_on(grid, onto):
    """grid's occupancy at the centres of `onto`'s voxels [R³] bool."""
    idx = grid.voxel_index(onto.centres())
    return (idx >= 0) & grid.occ.reshape(-1)[idx.clamp_min(0)]


def test_a_mirrored_view_sees_the_reflected_world_flipped(duck_views):
    f = duck_views[1]
    plane = MirrorPlane(torch.nn.functional.normalize(torch.tensor([0.3, 1.0, -0.2]), dim=0), 0.05)
    m = mirror_frame(f, plane)
    assert m.name == "v1.mirror.png" and torch.equal(m.image, f.image.flip(1)) and torch.equal(m.mask, f.mask.flip(1))
    assert torch.linalg.det(m.viewmat[:3, :3].double()) == pytest.approx(1.0, abs=1e-5)  # a camera, not a mirror
    points = torch.randn(20, 3, generator=torch.Generator().manual_seed(0)) * 0.3
    uv, z = project_points(points, f.viewmat, f.K)
    uv_m, z_m = project_points(reflect(points, plane.normal[None], torch.tensor([plane.offset]))[0], m.viewmat, m.K)
    assert torch.allclose(z_m, z, atol=1e-4)
    assert torch.allclose(uv_m[:, 0], f.width - uv[:, 0], atol=1e-3) and torch.allclose(uv_m[:, 1], uv[:, 1], atol=1e-3)
    twice = mirror_frame(m, plane)
    assert torch.allclose(twice.viewmat, f.viewmat, atol=1e-5) and torch.equal(twice.K, f.K)
    assert torch.equal(twice.image, f.image)


def test_no_mirror_without_the_gain(duck_views):
    record = mirror_check(duck_views, min_gain=1.0, max_missed=1.0, directions=20)
    assert not record["used"] and record["leave_one_out_iou_mirrored"] >= record["leave_one_out_iou"]


def test_no_mirror_where_its_views_would_cut_the_photos_masks(duck_views):
    """A duck with one wing is no longer symmetric: the best plane's mirror images would cut the
    wing (or its like) out of the photos' masks, so the check fails on what it misses."""

    def crooked(p):
        return duck(p) | ((p[:, 0] + 0.05) ** 2 + (p[:, 1] - 0.3) ** 2 + (p[:, 2] - 0.1) ** 2 < 0.13**2)

    views = frames_of(crooked, [camera(a, e) for a, e in ((20, 20), (105, 35), (200, 15), (290, 30))])
    record = mirror_check(views, min_gain=0.0, max_missed=0.02, directions=60)
    assert record["missed"] > 0.02 and not record["used"], record


def test_an_outline_view_teaches_its_mask_and_not_its_image():
    """A view with shows_colour=False (an "outline" mirror view) trains opacity away from outside
    its mask only: another image changes nothing, another mask changes the model, and a mask that
    allows matter everywhere asks nothing of the model at that view."""
    from conftest import ring_w2c

    from wgs.gaussians.splats import create_splats
    from wgs.gaussians.trainer import TrainConfig, train_gaussians
    from wgs.scene.dataset import Frame

    gen = torch.Generator().manual_seed(0)
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
    w2c = [torch.tensor(m, dtype=torch.float32) for m in ring_w2c(radius=2.0)]
    disc = ((torch.arange(16)[:, None] - 7.5) ** 2 + (torch.arange(16)[None] - 7.5) ** 2 < 30).float()
    photo = Frame(K, w2c[0], 16, 16, name="a.png", image=torch.rand(16, 16, 3, generator=gen), mask=disc)
    points, colours = torch.randn(60, 3, generator=gen) * 0.2, torch.rand(60, 3, generator=gen)
    cfg = TrainConfig(iterations=20, refine_start=100, floater_every=0, log_every=1)

    def trained(image, mask):
        outline = Frame(K, w2c[1], 16, 16, name="b.mirror.png", image=image, mask=mask, shows_colour=False)
        splats = create_splats(points, colours, torch.full((60,), 0.05), 0)
        return train_gaussians(splats, [photo, outline], cfg, torch.device("cpu"), extent=1.0, seed=0).splats

    base = trained(torch.rand(16, 16, 3, generator=gen), disc)
    other_image = trained(torch.rand(16, 16, 3, generator=gen), disc)
    other_mask = trained(torch.rand(16, 16, 3, generator=gen), disc.flip(0).roll(4, 1))
    for k in base:
        assert torch.allclose(base[k], other_image[k], atol=1e-6), k
    assert max(float((base[k] - other_mask[k]).abs().max()) for k in base if base[k].numel()) > 1e-3

    outline = Frame(
        K,
        w2c[1],
        16,
        16,
        name="b.mirror.png",
        image=torch.zeros(16, 16, 3),
        mask=torch.ones(16, 16),
        shows_colour=False,
    )
    splats = create_splats(points, colours, torch.full((60,), 0.05), 0)
    res = train_gaussians(splats, [outline], cfg, torch.device("cpu"), extent=1.0, seed=0)
    assert res.losses == [0.0] * cfg.iterations
