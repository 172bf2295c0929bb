"""`python -m tools.bench shape`'s measure of what S knows at the test views."""

from tools.bench import S_THRESHOLDS, silhouette_knowledge
from wgs.workspace import Workspace


def test_what_s_knows_at_the_test_views(finished_workspace):
    base, _ = finished_workspace
    res = silhouette_knowledge(Workspace(base / "ws"))
    assert set(res["iou"]) == {"S", "hull", "coarse"}
    assert all(0.0 < v <= 1.0 for v in res["iou"].values())
    under = [res["under"][str(t)] for t in S_THRESHOLDS]
    for lo, hi in zip(under, under[1:], strict=False):  # a higher threshold calls more pixels background
        assert lo["hull_excess"] <= hi["hull_excess"] and lo["object"] <= hi["object"]
    assert all(0.0 <= u["hull_excess"] <= 1.0 and 0.0 <= u["object"] <= 1.0 for u in under)


def test_a_scene_without_masks_has_nothing_to_measure(finished_workspace, tmp_path):
    import json
    import shutil

    base, _ = finished_workspace
    shutil.copytree(base / "ws" / "scene", tmp_path / "ws" / "scene")
    info = tmp_path / "ws" / "scene" / "scene.json"
    info.write_text(json.dumps(json.loads(info.read_text()) | {"has_masks": False}))
    assert silhouette_knowledge(Workspace(tmp_path / "ws")) == {}  # no masks: no hull, no S
