"""The fine stage's pseudo-view weight over the iterations."""

from wgs.config import FineConfig
from wgs.stages.s5_fine import pseudo_schedule


def test_default_keeps_pseudo_views_to_the_end():
    cfg = FineConfig(iterations=1000)
    w = pseudo_schedule(cfg)
    assert w(0) == w(500) == w(1000) == 1.0


def test_gaussianobject_schedule_ramps_then_stops():
    w = pseudo_schedule(FineConfig(iterations=1000, pseudo_weight_start=1.0, pseudo_weight_end=0.5, pseudo_until=0.7))
    assert w(0) == 1.0 and abs(w(350) - 0.75) < 1e-12 and abs(w(700) - 0.5) < 1e-12
    assert w(701) == 0.0
