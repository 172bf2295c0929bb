"""Fine stage only on a base workspace's stages (symlinked), with overrides; G_f PSNR and
silhouette IoU at all test views.
usage: python xp_fine.py BASE TAG '{"iterations": 2500}' [REPAIR_DIR]"""

import json
import sys
import time
from pathlib import Path

import torch

from wgs.config import resolve
from wgs.gaussians.splats import load_checkpoint
from wgs.scene.dataset import load_prepared
from wgs.stages.eval.scoring import evaluate_model
from wgs.stages.registry import run_stage
from wgs.stages.shared import background_for
from wgs.stages.stage import StageEnv
from wgs.workspace import STAGE_DIRS, Workspace


def test_scores(ws: Workspace, stage: str) -> dict[str, float]:
    """Mean PSNR and (where the test views have masks) silhouette IoU over all test views."""
    scene = load_prepared(ws.stage_dir("prepare"), load_test_images=True)
    splats = load_checkpoint(ws.output(stage, "model"), scene.norm)[0]
    per = evaluate_model(splats, scene.test, torch.device("cpu"), background_for(scene), None)
    return {k: round(sum(v.values()) / len(v), 4) for k, v in per.items() if k in ("psnr", "silhouette_iou")}


if __name__ == "__main__":
    base, tag, over = Path(sys.argv[1]).resolve(), sys.argv[2], json.loads(sys.argv[3])
    repair = Path(sys.argv[4]).resolve() if len(sys.argv) > 4 else None
    root = Path("fx") / tag
    root.mkdir(parents=True, exist_ok=True)
    for stage in ("prepare", "coarse", "mask_data", "finetune", "repair"):
        link = root / STAGE_DIRS[stage]
        if not link.exists():
            link.symlink_to(repair if stage == "repair" and repair else base / STAGE_DIRS[stage])
    ws = Workspace(root)
    seed = int(over.pop("seed", 0))
    t0 = time.perf_counter()
    run_stage("fine", ws, resolve("fine", cli=over), StageEnv(torch.device("cpu"), seed), force=True)
    secs = time.perf_counter() - t0
    res = {
        "tag": tag,
        "over": over,
        "seed": seed,
        "repair": str(repair),
        **test_scores(ws, "fine"),
        "fine_s": round(secs, 1),
    }
    print(json.dumps(res), flush=True)
    with open("fine_results.jsonl", "a") as fh:
        fh.write(json.dumps(res) + "\n")
