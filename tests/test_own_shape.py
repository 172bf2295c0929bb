"""Shape from the object's own evidence (`shape.own_shape`): generated solids from 4 photos around
them (make_scene's round, boxy and thin-parted kinds). A vase becomes a solid of revolution that
beats the hull from above, a box keeps its corners, a mug's thin handle survives, every real mask
pixel keeps an occupied voxel on its ray, and `wgs suggest`'s photo bounds more than most others."""

import functools
import math

import make_scene
import numpy as np
import pytest
import torch
from conftest import generated_frames, run_wgs

from wgs.shape.hull import box_rays, march, silhouette, visual_hull_grid
from wgs.shape.next_view import describe_direction, loose_voxels, suggest_view
from wgs.shape.opening import opening
from wgs.shape.own_shape import OwnShapeParams, own_shape
from wgs.shape.revolution import revolved, revolved_torch, rotation_matrices, spread_order
from wgs.shape.scores import mean_scores, silhouette_scores

SIZE, RESOLUTION = 64, 48


def capture(kind: str, seed: int = 5):
    """4 photos around a generated object from 15-45 degrees above, views from 80 degrees above, and
    views spread over the whole sphere."""
    rng = np.random.default_rng(seed)
    obj = make_scene.make_shape(kind, rng)
    above = [
        make_scene.RADIUS * np.array([0.17 * math.cos(a), 0.17 * math.sin(a), 0.985]) for a in (0.4, 2.0, 3.6, 5.2)
    ]
    eyes = {
        "train": make_scene.camera_positions(4, rng, True),
        "above": above,
        "sphere": make_scene.sphere_positions(12),
    }
    return generated_frames(obj, eyes, SIZE)


def iou_at(grid, frames) -> float:
    return mean_scores({f.name: silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5) for f in frames})["iou"]


@functools.cache
def shaped(kind: str):
    """(views, hull, own shape, record) of a generated object's 4-photo capture."""
    views = capture(kind)
    hull = visual_hull_grid(views["train"], RESOLUTION, tolerate=0)
    shape, record = own_shape(hull, views["train"], OwnShapeParams())
    return views, hull, shape, record


def test_a_vase_becomes_round_and_beats_the_hull_from_above():
    views, hull, shape, record = shaped("vase")
    assert record["revolution"]["used"]
    assert iou_at(shape, views["above"]) > iou_at(hull, views["above"]) + 0.03
    assert iou_at(shape, views["sphere"]) > iou_at(hull, views["sphere"])


def test_a_box_keeps_its_corners():
    views, hull, shape, record = shaped("box")
    assert not record["revolution"]["used"]
    assert iou_at(shape, views["sphere"]) >= iou_at(hull, views["sphere"]) - 0.005
    # the corners the photos show are still there: nothing of the true silhouettes is lost from above
    lost = [
        silhouette_scores(silhouette(shape, f)[0], f.mask > 0.5)["missed"]
        - silhouette_scores(silhouette(hull, f)[0], f.mask > 0.5)["missed"]
        for f in views["above"]
    ]
    assert max(lost) < 0.01


def test_a_thin_handle_survives():
    views, hull, shape, record = shaped("mug")
    assert not record["revolution"]["used"]
    for f in views["sphere"]:  # no view loses more of the mug than the hull does
        before = silhouette_scores(silhouette(hull, f)[0], f.mask > 0.5)["missed"]
        assert silhouette_scores(silhouette(shape, f)[0], f.mask > 0.5)["missed"] <= before + 0.01


@pytest.mark.parametrize("kind", ["vase", "box", "mug"])
def test_every_real_mask_pixel_keeps_an_occupied_voxel_on_its_ray(kind):
    views, hull, shape, _ = shaped(kind)
    occ = torch.cat([shape.occ.reshape(-1), torch.zeros(1, dtype=torch.bool)])
    for f in views["train"]:
        covered = silhouette(hull, f)[0] & (f.mask > 0.5)  # what the hull gave the mask, the shape keeps
        pixels = covered.reshape(-1).nonzero()[:, 0]
        for _, vox, _ in march(shape, box_rays(shape, f, pixels)):
            assert occ[vox].any(-1).all()


@pytest.mark.parametrize("kind", ["vase", "box", "mug"])
def test_the_shape_stays_inside_the_hull(kind):
    _, hull, shape, _ = shaped(kind)
    assert not (shape.occ & ~hull.occ).any()


def test_steps_switched_off_leave_the_hull():
    views = capture("vase")
    hull = visual_hull_grid(views["train"], 32, tolerate=0)
    shape, record = own_shape(hull, views["train"], OwnShapeParams(shape_revolution=False, shape_smooth=False))
    assert torch.equal(shape.occ, hull.occ) and record["restored"] == 0


def test_rotations_and_their_order():
    rots = rotation_matrices(torch.tensor([0.0, 0.0, 2.0]), 4)
    assert torch.allclose(rots[1] @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(rots @ rots.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-6)
    assert sorted(spread_order(24)) == list(range(24)) and spread_order(8)[:3] == [0, 4, 2]


def test_revolution_fast_path_matches_reference():
    """The numba kernel keeps the voxels the torch reference keeps, on a box with a ball on it
    (64³, a solid of revolution about a tilted line off the centre)."""
    from wgs.shape.hull import HullGrid

    c = (torch.arange(64) + 0.5) / 64 * 2 - 1
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    occ = ((x.abs() < 0.7) & (y.abs() < 0.6) & (z.abs() < 0.8)) | (x * x + y * y + (z - 0.5) ** 2 < 0.3)
    grid = HullGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), occ)
    for axis in ([0.1, 0.2, 1.0], [1.0, 0.0, 0.0], [0.3, -0.5, 0.2]):
        line = (torch.tensor([0.01, 0.02, 0.0]), torch.nn.functional.normalize(torch.tensor(axis), dim=0))
        fast, reference = revolved(grid, *line).occ, revolved_torch(grid, *line).occ
        assert torch.equal(fast, reference) and 0 < int(reference.sum()) < int(occ.sum())


def test_a_ball_is_its_own_revolution_and_opening():
    from wgs.shape.hull import HullGrid

    r = 24
    c = (torch.arange(r) + 0.5) / r * 2 - 1
    x, y, z = torch.meshgrid(c, c, c, indexing="ij")
    ball = HullGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), x * x + y * y + z * z < 0.8**2)
    spun = revolved(ball, torch.zeros(3), torch.tensor([0.3, 0.2, 0.9]))
    assert float(spun.occ.sum()) / float(ball.occ.sum()) > 0.97
    kept = opening(ball, 0.3).occ  # a ball is open at any smaller radius, up to the grid's steps
    assert not (kept & ~ball.occ).any() and float(kept.sum()) / float(ball.occ.sum()) > 0.97
    cube = ball.with_occupancy((x.abs() < 0.7) & (y.abs() < 0.7) & (z.abs() < 0.7))
    assert int(opening(cube, 0.4).occ.sum()) < int(cube.occ.sum())  # corners go


def test_the_suggested_photo_bounds_more_than_the_median_direction():
    views, hull, _, _ = shaped("vase")
    record = suggest_view(*loose_voxels(hull), views["train"], candidates=40)
    assert record["bounds"] > record["median_bounds"]
    assert "photo train_" in record["sentence"] or "above" in record["sentence"]


def test_the_sentence_names_side_and_height():
    views = shaped("box")[0]
    photos = views["train"]
    sentence, numbers = describe_direction(views["above"][0], photos)
    assert sentence.startswith("from straight above") and numbers["elevation_deg"] > 75
    sentence, _ = describe_direction(photos[1], photos)
    assert sentence == f"from the side, near photo {photos[1].name}"


def test_suggest_needs_a_prepared_scene(tmp_path):
    r = run_wgs(["-w", str(tmp_path / "ws"), "suggest"], tmp_path)
    assert r.returncode == 2 and "wgs prepare" in r.stderr
