"""How many held-out pilots the coarse stage's stop needs: each pilot's curve kept apart.

For a finished `wgs all` workspace: the coarse stage's pilots (`train_pilot`, the recorded
settings, one per photo up to 4, spread over the photos' order as the stage picks them) without
their end at a plateau shown past iterations / margin, each curve kept; then the stop the rule
would make from K of them for K = 1..4 (spread the same way: K = 2 takes the 1st and 3rd), and
from all 4 cut where each pilot's own curve first shows that plateau (`plateau_past`, what the
stage does: "proof" below).

    python tools/experiments/xp_pilot_count.py WORKSPACE...
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root, run as a script from anywhere

from wgs.gaussians.stopping import Curve, mean_curve, plateau_iteration, smoothed, stop_iteration  # noqa: E402
from wgs.scene.dataset import load_prepared  # noqa: E402
from wgs.stages.coarse.run import train_pilot  # noqa: E402
from wgs.stages.shared import recorded_config  # noqa: E402
from wgs.threads import map_in_processes  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def proof_cut(curve: Curve, point: float, tolerance_db: float) -> Curve:
    """`curve` up to the first score past `point` that beats every score up to `point` by more
    than `tolerance_db` (its plateau then lies past `point`); the whole curve where none does."""
    before = max((s for it, s in curve if it <= point), default=math.inf)
    for k, (it, s) in enumerate(curve):
        if it > point and s > before + tolerance_db:
            return curve[: k + 1]
    return curve


def stop_from(curves: list[Curve], cfg) -> tuple[int, int]:
    mean = smoothed(mean_curve(curves), cfg.refine_every)
    plateau = plateau_iteration(mean, cfg.stop_tolerance_db)
    return plateau, stop_iteration(plateau, cfg.stop_margin, cfg.stop_min_iterations, cfg.iterations)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    for root in args.workspaces:
        ws = Workspace(root)
        cfg = recorded_config(ws, "coarse")
        scene = load_prepared(ws.output("prepare", "prepared"))
        photos = [f.name for f in scene.colour_views]
        k = min(len(photos), 4)
        photos = [photos[i * len(photos) // k] for i in range(k)]
        t0 = time.perf_counter()
        jobs = [(ws, cfg, torch.device("cpu"), 0, name, False) for name in photos]
        curves = [c for _, c in sorted(map_in_processes(train_pilot, jobs, args.workers))]
        seconds = time.perf_counter() - t0
        print(f"## {root} ({seconds:.0f} s for {k} pilots; lengths {[c[-1][0] for c in curves]})")
        for n in range(1, k + 1):
            chosen = [curves[i * k // n] for i in range(n)]
            plateau, stop = stop_from(chosen, cfg)
            length = sum(c[-1][0] for c in chosen)
            print(f"  {n} pilot(s): plateau {plateau}, stop at {stop}, {length} pilot iterations")
        point = cfg.iterations / cfg.stop_margin
        cut = [proof_cut(c, point, cfg.stop_tolerance_db) for c in curves]
        plateau, stop = stop_from(cut, cfg)
        print(
            f"  {k} pilots, proof: plateau {plateau}, stop at {stop}, lengths {[c[-1][0] for c in cut]} "
            f"({sum(c[-1][0] for c in cut)} pilot iterations)"
        )


if __name__ == "__main__":
    main()
