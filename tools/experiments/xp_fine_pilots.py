"""Fine pilots: does something held out of the fine stage say where G_f stops gaining at the test views?

For a finished `wgs all` workspace: G_f trained as its fine stage trains it (the same start, pseudo
references and settings) at half size, with
- `--hold photo`: one photo held out (up to 4 pilots), its PSNR at that photo; the pseudo
  references come from G_c, which saw the held-out photo, so they carry some of it;
- `--hold pseudo`: every 4th pseudo reference held out (4 pilots, each a different quarter), the
  mean PSNR at those views against their pseudo references;
every 25 iterations. The pilots' mean curve (averaged over a densification period, as the coarse
pilots' is) is printed beside the workspace's own G_f test probe (5_fine/curve.json).

    python tools/experiments/xp_fine_pilots.py [--hold photo|pseudo] WORKSPACE...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root, run as a script from anywhere

from wgs.gaussians.callbacks import Probe  # noqa: E402
from wgs.gaussians.stopping import mean_curve, plateau_iteration, smoothed  # noqa: E402
from wgs.gaussians.trainer import render_frame, train_gaussians  # noqa: E402
from wgs.metrics import psnr  # noqa: E402
from wgs.scene.dataset import composite, halved, load_prepared  # noqa: E402
from wgs.stages.fine.run import fine_inputs  # noqa: E402
from wgs.stages.shared import recorded_config  # noqa: E402
from wgs.threads import map_in_processes  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402

EVERY = 25


def pilot(root: str, hold: str, held_out: str) -> list[tuple[int, float]]:
    ws = Workspace(Path(root))
    cfg = recorded_config(ws, "fine")
    device = torch.device("cpu")
    seed = 0
    inputs = fine_inputs(ws, cfg, device, seed)
    scene, bg = inputs.scene, inputs.background
    pseudo = inputs.pseudo(cfg)
    train = scene.train
    if hold == "photo":
        train = [f for f in scene.train if f.name != held_out]
        targets = [halved(next(f for f in scene.train if f.name == held_out))]
    else:
        quarter = int(held_out)
        keep = [i for i in range(len(pseudo.frames)) if i % 4 != quarter]
        targets = [halved(f) for i, f in enumerate(pseudo.frames) if i % 4 == quarter]
        pseudo = dataclasses.replace(
            pseudo, frames=[pseudo.frames[i] for i in keep], weights=[pseudo.weights[i] for i in keep]
        )
    refs = [composite(t.pixels, t.mask, bg) for t in targets]

    def score(splats) -> dict[str, float]:
        return {
            "psnr": sum(psnr(render_frame(splats, t, device, bg)[0], r) for t, r in zip(targets, refs, strict=True))
            / len(targets)
        }

    torch.manual_seed(seed)
    res = train_gaussians(
        inputs.splats,
        train,
        dataclasses.replace(cfg, half_size_until=1.0),
        device,
        extent=1.0,
        desc=f"fine pilot without {held_out}",
        seed=seed,
        has_masks=scene.has_masks,
        pseudo=pseudo,
        probe=Probe(score, every_s=math.inf, every_iterations=EVERY),
    )
    return [(int(p["iteration"]), p["psnr"]) for p in res.curve]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--hold", choices=("photo", "pseudo"), default="pseudo")
    args = ap.parse_args()
    for root in args.workspaces:
        ws = Workspace(root)
        scene = load_prepared(ws.output("prepare", "prepared"))
        photos = [f.name for f in scene.colour_views]
        k = min(4, len(photos))
        photos = [photos[i * len(photos) // k] for i in range(k)] if args.hold == "photo" else ["0", "1", "2", "3"]
        t0 = time.perf_counter()
        curves = dict(
            zip(
                photos,
                [
                    c
                    for _, c in sorted(
                        map_in_processes(pilot, [(str(root), args.hold, p) for p in photos], args.workers)
                    )
                ],
                strict=True,
            )
        )
        cfg = recorded_config(ws, "fine")
        mean = smoothed(mean_curve([curves[p] for p in photos]), cfg.refine_every)
        test = json.loads(ws.output("fine", "curve").read_text())["points"]
        test_curve = [(int(p["iteration"]), p["psnr"]) for p in test]
        print(f"## {root} ({time.perf_counter() - t0:.0f} s for {k} pilots)")
        print("pilots' mean (iteration, dB):", [(it, round(s, 2)) for it, s in mean if it % 100 == 0])
        print(
            f"pilots' plateau (0.1 dB): {plateau_iteration(mean, 0.1)}; best at "
            f"{max(mean, key=lambda p: p[1])[0]}; test probe's plateau (0.1 dB): "
            f"{plateau_iteration(test_curve, 0.1)}, best at {max(test_curve, key=lambda p: p[1])[0]} "
            f"({max(s for _, s in test_curve):.2f} dB, end {test_curve[-1][1]:.2f} dB)"
        )
        for p in photos:
            c = curves[p]
            print(f"  {p}: best at {max(c, key=lambda q: q[1])[0]} ({max(s for _, s in c):.2f}), end {c[-1][1]:.2f}")


if __name__ == "__main__":
    main()
