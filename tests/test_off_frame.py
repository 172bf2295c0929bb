"""Objects that run out of the photos: a generated close-up capture (`make_scene --close-up`), whose
training photos all crop the object while the test views stand back and see all of it. The hull
stays bounded where no photo sees, does not cut what a photo crops, G_c trains no worse than with
a hull that cuts, and G_f keeps away from a hull that cuts what the photos show."""

import math
from types import SimpleNamespace

import make_scene
import numpy as np
import pytest
import torch
from conftest import generated_frames

import wgs.shape.hull as hull
from wgs.config import resolve
from wgs.gaussians.trainer import render_frame, train_gaussians
from wgs.metrics import psnr
from wgs.scene.dataset import Frame, PreparedScene, composite
from wgs.shape.scores import HULL_CUT_LIMIT, hull_cut, mean_scores, silhouette_scores
from wgs.stages.fine.run import start_of
from wgs.stages.fine.settings import FineConfig
from wgs.stages.shared import initial_splats

SIZE = 64


def close_up(seed: int, n_around: int = 0):
    """(training frames, test frames, frames from all around) of make_scene's close-up capture,
    in the normalised world of its training cameras."""
    rng = np.random.default_rng(seed)
    parts = make_scene.make_object(rng)
    eyes = {
        "train": make_scene.camera_positions(4, rng, True, close_up=True),
        "test": make_scene.camera_positions(6, rng, False, close_up=True),
    }
    golden = math.pi * (3 - math.sqrt(5))
    eyes["around"] = [
        make_scene.STAND_BACK_DISTANCE
        * np.array([math.sqrt(1 - z * z) * math.cos(i * golden), math.sqrt(1 - z * z) * math.sin(i * golden), z])
        for i, z in enumerate(1 - 2 * (np.arange(n_around) + 0.5) / max(n_around, 1))
    ]
    out = generated_frames(parts, eyes, SIZE)
    return out["train"], out["test"], out["around"]


def touches_edge(mask: torch.Tensor) -> bool:
    m = mask > 0.5
    return bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())


def volume(grid) -> float:
    return float(grid.occ.sum()) * float(grid.cell.prod())


@pytest.fixture(scope="module", params=[0, 1])
def capture(request):
    return close_up(request.param, n_around=24)


def test_the_close_up_crops_every_training_photo_and_no_test_view(capture):
    train, test, around = capture
    assert all(touches_edge(f.mask) for f in train)
    assert not any(touches_edge(f.mask) for f in test + around)


def test_the_hull_stays_bounded_and_does_not_cut_what_the_photos_crop(capture):
    """The strict hull's volume within 2x that of the hull of 24 views from all around; the border
    rule's ("object") fills what no photo bounds, and "background" cuts more of the object at the
    test views."""
    train, test, around = capture
    reference = volume(hull.visual_hull_grid(around, 64, tolerate=0))
    grids = {rule: hull.visual_hull_grid(train, 64, tolerate=0, off_frame=rule) for rule in hull.OFF_FRAME}
    ratio = {rule: volume(g) / reference for rule, g in grids.items()}
    missed = {
        rule: mean_scores({f.name: silhouette_scores(hull.silhouette(g, f)[0], f.mask > 0.5) for f in test})["missed"]
        for rule, g in grids.items()
    }
    assert 1.0 <= ratio["abstain"] < 2.0, ratio
    assert ratio["object"] > ratio["abstain"], ratio
    assert missed["abstain"] < missed["background"], missed


def test_a_close_up_trains_g_c_no_worse_than_a_hull_that_cuts():
    """G_c's test PSNR from the "abstain" rule's coarse init is at least that from the hull that
    calls everything outside a frame background (the fast preset's coarse stage, one model)."""
    train, test, _ = close_up(0)
    scene = PreparedScene({"has_masks": True, "train_names": [f.name for f in train]}, None, train, test)
    cfg = resolve("coarse", "fast", cli={"iterations": 200, "refine_stop": 150})
    scores = {}
    for rule in ("abstain", "background"):
        grid = hull.visual_hull_grid(train, cfg.hull_resolution, off_frame=rule)
        init = initial_splats(scene, cfg, 0, grid)
        torch.manual_seed(0)
        splats = train_gaussians(init, train, cfg, torch.device("cpu"), extent=1.0, seed=0).splats
        bg = torch.ones(3)
        scores[rule] = float(
            np.mean(
                [
                    float(
                        psnr(
                            render_frame(splats, f, torch.device("cpu"), bg)[0].clamp(0, 1),
                            composite(f.image, f.mask, bg),
                        )
                    )
                    for f in test
                ]
            )
        )
    assert scores["abstain"] >= scores["background"] - 0.05, scores


def test_g_f_keeps_away_from_a_hull_that_cuts_what_the_photos_show():
    """Where the hull of the other photos leaves out part of a photo's mask (here one mask misses
    half the object), G_f starts from G_c; with masks that agree it starts from the hull."""
    _, _, around = close_up(1, n_around=6)
    bad = [Frame(f.K, f.viewmat, f.width, f.height, name=f.name, mask=f.mask.clone()) for f in around]
    bad[0].mask[:, : SIZE // 2] = 0.0
    whole = SimpleNamespace(has_masks=True, photos=around)
    cut = SimpleNamespace(has_masks=True, photos=bad)
    assert hull_cut(around, 64) < HULL_CUT_LIMIT < hull_cut(bad, 64)
    assert start_of(FineConfig(hull_resolution=64), whole) == "hull"
    assert start_of(FineConfig(hull_resolution=64), cut) == "coarse"
    assert start_of(FineConfig(hull_resolution=64, start="hull"), cut) == "hull"
    assert start_of(FineConfig(hull_resolution=64, start="coarse"), whole) == "coarse"
    assert start_of(FineConfig(hull_resolution=64), SimpleNamespace(has_masks=False, photos=[])) == "coarse"
