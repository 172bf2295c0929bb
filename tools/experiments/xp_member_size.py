"""The ensemble's other models at half size for a share of their schedule: can the photos say
which share a scene wants?

For a finished `wgs all` workspace: a coarse model like an ensemble member (its seed, the coarse
stage's recorded settings and stop) trained on all photos but one, with `half_size_until` set to
each `--shares` value, scored at the photo held out, at full size, at the end. Up to `--folds`
photos are held out in turn (spread over the photos' order, as the pilots are). Printed beside the
workspace's own G_f test PSNR, to compare with runs of `[coarse] member_half_size_until` set to
the same shares.

    python tools/experiments/xp_member_size.py [--shares 0.6 1.0] [--folds 2] WORKSPACE...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root, run as a script from anywhere

from wgs.gaussians.trainer import render_frame, train_gaussians  # noqa: E402
from wgs.metrics import psnr  # noqa: E402
from wgs.scene.dataset import composite, load_prepared  # noqa: E402
from wgs.stages.shared import background_for, initial_splats, recorded_config  # noqa: E402
from wgs.threads import map_in_processes  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def fold(root: str, share: float, held_out: str) -> tuple[float, float]:
    """(held-out PSNR at full size, seconds) of one model trained without `held_out`."""
    ws = Workspace(Path(root))
    cfg = recorded_config(ws, "coarse")
    manifest = json.loads((Path(root) / "1_coarse" / "manifest.json").read_text())
    stop = (manifest.get("stopping") or {}).get("stop_at") or cfg.iterations
    seed = int(manifest.get("seed", 0)) + 1
    device = torch.device("cpu")
    scene = load_prepared(ws.output("prepare", "prepared"))
    train = dataclasses.replace(scene, train=[f for f in scene.train if f.name != held_out])
    target = next(f for f in scene.train if f.name == held_out)
    bg = background_for(scene)
    t0 = time.perf_counter()
    torch.manual_seed(seed)
    res = train_gaussians(
        initial_splats(train, cfg, seed),
        train.train,
        dataclasses.replace(cfg, half_size_until=share, end_iteration=stop),
        device,
        extent=1.0,
        desc=f"without {held_out}, half size until {share:g}",
        seed=seed,
        has_masks=scene.has_masks,
    )
    score = psnr(render_frame(res.splats, target, device, bg)[0], composite(target.pixels, target.mask, bg))
    return float(score), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--shares", nargs="+", type=float, default=[0.6, 1.0])
    ap.add_argument("--folds", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    for root in args.workspaces:
        ws = Workspace(root)
        scene = load_prepared(ws.output("prepare", "prepared"))
        photos = [f.name for f in scene.colour_views]
        k = min(args.folds, len(photos))
        photos = [photos[i * len(photos) // k] for i in range(k)]
        jobs = [(str(root), s, p) for s in args.shares for p in photos]
        found = dict(sorted(map_in_processes(fold, jobs, args.workers)))
        results = json.loads(ws.output("eval", "results").read_text())
        print(f"## {root}: G_f {results['psnr']:.3f} dB at its test views")
        for si, s in enumerate(args.shares):
            scores = [found[si * k + j][0] for j in range(k)]
            secs = sum(found[si * k + j][1] for j in range(k))
            print(
                f"  half size until {s:g}: held-out PSNR mean {statistics.fmean(scores):.3f} dB "
                f"({', '.join(f'{x:.2f}' for x in scores)}), {secs:.0f} s"
            )


if __name__ == "__main__":
    main()
