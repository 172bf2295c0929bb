"""Stage 0: import a scene into `WS/scene/`."""

from __future__ import annotations

from pathlib import Path

from ..config import PrepareConfig, as_dict
from ..errors import InputError
from ..progress import log
from ..scene.prepare import load_scene_for_prepare, prepare, scene_inputs_digest
from ..workspace import Workspace


def run_prepare(ws: Workspace, scene_dir: Path, cfg: PrepareConfig, force: bool = False) -> bool:
    """Import `scene_dir`; returns False when the workspace was already up to date."""
    scene = load_scene_for_prepare(scene_dir, cfg)
    config = as_dict(cfg)
    with ws.lock():
        fp = ws.begin("scene", config, {"source": str(scene_dir.resolve()), "inputs": scene_inputs_digest(scene)},
                      force)
        if fp is None:
            return False
        held = ((ws.manifest("scene") or {}).get("summary") or {}).get("source")
        if held is not None and Path(held) != scene_dir.resolve() and not force:
            raise InputError(f"this workspace holds another scene ({held}): use a new -w folder, or add --force "
                             "to replace it (every stage is then recomputed)", ws.root)
        for note in scene.notes:
            log(f"  note: {note}")
        log(f"prepare: {scene.format} scene, {len(scene.train)} training + {len(scene.test)} test views")
        with ws.stage_run("scene", config, fp) as run:
            info = prepare(scene, cfg, run)
            run.record["summary"] = {
                "source": info["source"], "format": info["format"], "num_train": len(info["train_names"]),
                "num_test": len(info["test_names"]), "resolution": info["resolution"],
                "has_masks": info["has_masks"],
            }
    log(f"prepare: wrote {ws.stage_dir('scene')}")
    return True
