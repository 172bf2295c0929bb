"""The eval stage's shape scores: how fat the visual hull is at the test views and by leave-one-out,
and the notes on where the masks came from."""

from __future__ import annotations

from typing import Any

from ...errors import InputError
from ...progress import log
from ...scene.dataset import Frame
from ...shape.hull import HullGrid, silhouette, visual_hull_grid
from ...shape.own_shape import describe as describe_own_shape
from ...shape.scores import leave_one_out, mean_scores, silhouette_scores


def shape_reference(
    scene, frames: list[Frame], resolution: int, carved: HullGrid | None = None
) -> dict[str, Any] | None:
    """How fat the visual hull is: the hull of all training masks (every mask agreeing) scored at
    the test views that have masks, the same for the repair stage's carved hull where there is one,
    and the leave-one-out estimate that needs no test views (the hull of the other photos' masks at
    each photo's camera; mirror views play no part in it). None without masks, or where the training
    masks share no region."""
    if not scene.has_masks:
        return None
    try:
        grid = visual_hull_grid(scene.train, resolution, tolerate=0)
        loo = leave_one_out(scene.photos, resolution) if len(scene.photos) >= 2 else {}
    except InputError:
        log("eval: the training masks share no region (every mask agreeing) -> no visual-hull scores")
        return None
    with_mask = [f for f in frames if f.mask is not None]
    test = {f.name: silhouette_scores(silhouette(grid, f)[0], f.object_pixels) for f in with_mask}
    carved_test = (
        {f.name: silhouette_scores(silhouette(carved, f)[0], f.object_pixels) for f in with_mask}
        if carved is not None
        else {}
    )
    return {
        "hull_test": mean_scores(test),
        "carved_hull_test": mean_scores(carved_test),
        "leave_one_out": mean_scores(loo),
        "hull_resolution": resolution,
        "hull_test_per_view": test,
        "carved_hull_test_per_view": carved_test,
        "leave_one_out_per_view": loo,
    }


def masks_note(scene) -> str | None:
    """Where the masks came from when wgs made them (the truth is composited with them), or why the
    automatic ones were not used; that no masks checked poses wgs found itself; and which training
    photos crop the object."""
    masks = scene.info.get("masks") or {}
    notes = []
    if masks.get("source") == "auto":
        notes.append(
            "The masks are automatic (`wgs prepare --masks auto`): the test views' ground truth is "
            "composited with them, so these scores measure against wgs's own idea of the object's outline."
        )
    elif masks.get("auto_failed"):
        notes.append(
            f"No masks: the automatic ones were not used ({masks['auto_failed']}), so there is no visual "
            "hull and no silhouette score; `wgs prepare --masks DIR` takes yours."
        )
    if scene.info.get("poses_checked") is False:
        notes.append(
            "wgs posed these photos itself, and no masks of yours checked the poses: repeating textures or a "
            "symmetric object can be posed wrongly, and a model on wrong poses still fits its training views. "
            "Masks of your own (`--masks DIR`) have the hull of the other photos check each pose."
        )
    if masks.get("training_cropped"):
        notes.append(
            f"Training photos that crop the object (their mask reaches the frame's edge): "
            f"{', '.join(masks['training_cropped'])}; photos that hold the whole object bound more of it."
        )
    return " ".join(notes) or None


def shape_line(coarse: dict, fine: dict, shape: dict) -> str:
    """One line of silhouette IoUs: hull, G_c and G_f at the views eval scored (the test views, or
    the training photos where the scene has none), and the leave-one-out estimate."""
    parts = []
    if shape["hull_test"] is not None:
        parts.append(f"visual hull {shape['hull_test']['iou']:.3f}")
    if shape.get("carved_hull_test") is not None:
        parts.append(f"carved hull {shape['carved_hull_test']['iou']:.3f}")
    if coarse.get("silhouette_iou") is not None:
        parts.append(f"coarse {coarse['silhouette_iou']:.3f} -> fine {fine['silhouette_iou']:.3f}")
    views = "training photos (no test views)" if fine.get("views") == "training" else "test views"
    head = f"silhouette IoU at the {views}: " + ", ".join(parts) if parts else "no test masks"
    loo, mirror = shape["leave_one_out"], shape.get("mirror")
    if loo is not None:
        head += f"; leave-one-out estimate (hull of the other photos' masks at each photo's camera) {loo['iou']:.3f}"
    if mirror:
        taught = {"outline": " (their outlines)", "full": " (outlines and colours)"}.get(mirror.get("views"), "")
        head += (
            f"; the photos' mirror images {'are' if mirror['used'] else 'are not'} training views"
            f"{taught if mirror['used'] else ''} "
            f"(leave-one-out IoU {mirror['leave_one_out_iou']:.3f} -> {mirror['leave_one_out_iou_mirrored']:.3f}"
            " with the mirror)"
        )
    if shape.get("own_shape"):
        head += f"; the hull shaped by the photos' masks: {describe_own_shape(shape['own_shape'])}"
    return head
