"""The coarse ensemble's size: does the members' own agreement say how many a scene needs?

For each finished `wgs all` workspace (default settings, 6 coarse models) and each size K: a copy
whose repair, fine and eval stages rerun on its first K coarse models (the coarse stage's record
says K), G_f's PSNR and silhouette IoU at the test views; beside them, what the coarse stage could
see before training more members: the members' spread at 8 novel views between the training
cameras (`scene.orbit.novel_views`, 2 per pair), as the standard error of the K-member mean in dB,
-10 log10(var_K / K) over the pixels any member covers.

    python tools/experiments/xp_ensemble_size.py --out DIR [--sizes 2 4] WORKSPACE...

A copy takes about the repair, fine and eval stages' time (1-1.5 min on lego at 200 px, 2 cores).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root, run as a script from anywhere

from wgs.gaussians.trainer import render_frame  # noqa: E402
from wgs.scene.dataset import load_prepared  # noqa: E402
from wgs.scene.orbit import novel_views  # noqa: E402
from wgs.stages.shared import background_for, coarse_members  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def spread_db(ws: Workspace, sizes: list[int]) -> dict[int, float]:
    """The standard error of the first K members' mean render, in dB, for each K in `sizes`."""
    scene = load_prepared(ws.output("prepare", "prepared"))
    members = coarse_members(ws, scene, torch.device("cpu"))
    bg = background_for(scene)
    rgb, alpha = [], []
    for frame, _ in novel_views(scene.train, 2, 0.3, 0.7, 0):
        renders = [render_frame(m, frame, torch.device("cpu"), bg) for m in members]
        rgb.append(torch.stack([r for r, _ in renders]))
        alpha.append(torch.stack([a for _, a in renders]))
    colours, covered = torch.stack(rgb), (torch.stack(alpha) > 0.5).any(1)[..., 0]  # [V, M, H, W, 3], [V, H, W]
    return {k: -10 * math.log10(colours[:, :k].var(1).mean(-1)[covered].mean().item() / k) for k in sizes}


def rerun(src: Path, out: Path, k: int) -> dict:
    """Repair, fine and eval of a copy of `src` on its first `k` coarse models; G_f's scores."""
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("4_repair", "5_fine", "6_eval"))
    manifest = out / "1_coarse" / "manifest.json"
    record = json.loads(manifest.read_text())
    record["ensemble"] = k
    manifest.write_text(json.dumps(record, indent=1))
    for stage in ("repair", "fine", "eval"):
        subprocess.run([sys.executable, "-m", "wgs", "-q", "-w", str(out), stage], check=True)
    res = json.loads((out / "6_eval" / "results.json").read_text())
    return {"psnr": res["psnr"], "iou": res["silhouette_iou"]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("workspaces", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2, 4])
    args = ap.parse_args()
    print("| workspace | K | spread (dB) | G_f PSNR | G_f IoU |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for src in args.workspaces:
        full = int(json.loads((src / "1_coarse" / "manifest.json").read_text())["ensemble"])
        spread = spread_db(Workspace(src), [*args.sizes, full])
        own = json.loads((src / "6_eval" / "results.json").read_text())
        rows = {full: {"psnr": own["psnr"], "iou": own["silhouette_iou"]}}
        for k in args.sizes:
            rows[k] = rerun(src, args.out / f"{src.name}_k{k}", k)
        for k in sorted(rows):
            print(f"| {src.name} | {k} | {spread[k]:.1f} | {rows[k]['psnr']:.2f} | {rows[k]['iou']:.4f} |")


if __name__ == "__main__":
    main()
