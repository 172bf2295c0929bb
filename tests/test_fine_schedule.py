"""The fine stage's pseudo-view weight over the iterations and the model it starts from."""

from types import SimpleNamespace

import pytest

from wgs.config import resolve
from wgs.errors import InputError
from wgs.stages.fine.run import pseudo_schedule, start_of
from wgs.stages.fine.settings import FineConfig


def test_default_keeps_pseudo_views_to_the_end():
    cfg = FineConfig(iterations=1000)
    w = pseudo_schedule(cfg)
    assert w(0) == w(500) == w(1000) == 1.0


def test_gaussianobject_schedule_ramps_then_stops():
    w = pseudo_schedule(FineConfig(iterations=1000, pseudo_weight_start=1.0, pseudo_weight_end=0.5, pseudo_until=0.7))
    assert w(0) == 1.0 and abs(w(350) - 0.75) < 1e-12 and abs(w(700) - 0.5) < 1e-12
    assert w(701) == 0.0


def test_start_auto_is_g_c_without_masks_and_a_given_start_is_kept():
    """(With masks, auto asks whether the hull cuts the object: tests/test_off_frame.py.)"""
    without = SimpleNamespace(has_masks=False, photos=[])
    assert start_of(FineConfig(), without) == "coarse"
    assert start_of(FineConfig(start="hull"), without) == "hull"


def test_unknown_start_is_refused():
    with pytest.raises(InputError, match="'start' must be one of auto, coarse, hull"):
        resolve("fine", None, {"fine": {"start": "scratch"}}, {})
