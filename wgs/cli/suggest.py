"""`wgs suggest`: where one more photo would help the shape most."""

from __future__ import annotations

from dataclasses import dataclass

import click

from ..context import RunOptions
from ..errors import WgsError
from ..fields import option
from .main import workspace_option
from .options import settings_options


@dataclass
class SuggestSettings:
    resolution: int = option(64, "Voxels along the hull's box.", bounds=(16, None))


@click.command()
@settings_options(SuggestSettings)
@workspace_option
@click.pass_obj
def suggest(obj: RunOptions, resolution: int) -> None:
    """Say where one more photo would bound most of the shape that no photo bounds now (after
    `wgs prepare`; the scene needs masks): a sentence, and a preview from there in WS/suggest/."""
    from ..io import atomic_write_json
    from ..io.images import write_png
    from ..progress import results
    from ..scene.dataset import load_prepared
    from ..shape.hull import visual_hull_grid
    from ..shape.next_view import loose_voxels, preview, suggest_view

    ws = obj.ws()
    if ws.status("prepare") == "missing":
        raise WgsError("no prepared scene: run `wgs prepare SCENE` first", ws.root)
    scene = load_prepared(ws.output("prepare", "prepared"))
    if not scene.has_masks:
        raise WgsError("the scene has no masks, and the shape that photos bound comes from masks", ws.root)
    hull = visual_hull_grid(scene.train, resolution, tolerate=0)
    core, loose = loose_voxels(hull)
    record = suggest_view(core, loose, scene.photos)
    out = ws.root / "suggest"
    write_png(out / "preview.png", preview(hull, core, loose, record["camera"]))
    camera = record.pop("camera")
    atomic_write_json(out / "suggestion.json", {**record, "camera": camera.to_json()})
    results.print(
        f"suggest: one more photo {record['sentence']}: it would bound {record['bounds']:.0%} of the "
        f"shape no photo bounds now (a median direction: {record['median_bounds']:.0%}); preview "
        f"{out / 'preview.png'}",
        soft_wrap=True,
    )
