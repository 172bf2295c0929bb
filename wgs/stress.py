"""Slow robustness checks behind `make stress`.

    python -m wgs.stress kill-loop [--kills 14] [--out DIR]

kill-loop: runs `wgs all` on a generated scene once without interruption (the reference), then
once per kill point: starts it in a fresh workspace, SIGKILLs it at a moment spread evenly over the
reference run's duration (so every stage is hit in proportion to its time), reruns it (alternately
with --resume and without) until it finishes, and compares the results and the final model with the
reference. A last trial kills every few seconds until the run gets through. Prints one line per
trial and writes kill_loop.json.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from .workspace import STAGE_DIRS, Workspace

# Long enough that every stage spans several seconds on a 2-core CPU (the tests use a smaller one).
STRESS_TOML = """
[coarse]
iterations = 300
refine_start = 50
refine_every = 50
init_points = 800
hull_resolution = 32
[mask_data]
iterations = 300
refine_start = 50
refine_every = 50
init_points = 800
hull_resolution = 32
warmup = 100
pair_every = 50
[finetune]
d_steps = 150
d_channels = 8
d_batch = 4
u_max_steps = 60
u_channels = 8
u_eval_every = 10
u_patience = 100
eval_steps = 2
[repair]
steps = 2
[fine]
iterations = 300
refine_start = 50
refine_every = 50
"""


def wgs_command(ws: Path, scene: Path, cfg: Path, resume: bool, checkpoint_every: float) -> list[str]:
    return [sys.executable, "-m", "wgs", "-q", "--config", str(cfg), "--checkpoint-every", str(checkpoint_every),
            *(["--resume"] if resume else []), "-w", str(ws), "all", str(scene)]


def run_until_killed(cmd: list[str], after_s: float) -> tuple[int | None, float]:
    """Start `cmd`, SIGKILL it after `after_s` seconds unless it ended; (exit status or None, wall s)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        rc = proc.wait(timeout=after_s)
        return rc, time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        return None, time.perf_counter() - t0


def running_stage(ws: Path) -> str:
    """The first stage without a finished manifest: the one a kill interrupted."""
    w = Workspace(ws)
    for stage in STAGE_DIRS:
        if w.manifest(stage) is None:
            return stage
    return "after eval"


def outcome(ws: Path) -> dict[str, Any]:
    """What must not depend on interruptions: metrics and the final model's tensors."""
    res = json.loads((ws / STAGE_DIRS["eval"] / "results.json").read_text())
    keep = {k: res[k] for k in ("psnr", "ssim", "num_gaussians")}
    keep["coarse"] = {k: res["coarse"][k] for k in ("psnr", "ssim", "num_gaussians")}
    return keep


def max_param_difference(a: Path, b: Path) -> float:
    ca = torch.load(a / STAGE_DIRS["fine"] / "ckpt.pt", weights_only=True)["splats"]
    cb = torch.load(b / STAGE_DIRS["fine"] / "ckpt.pt", weights_only=True)["splats"]
    if ca.keys() != cb.keys() or any(ca[k].shape != cb[k].shape for k in ca):
        return float("inf")
    return max(float((ca[k] - cb[k]).abs().max()) for k in ca)


def kill_loop(out: Path, kills: int, checkpoint_every: float, hammer_s: float) -> dict[str, Any]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from make_scene import make_scene

    out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(out / "scene", seed=3, size=64, n_train=4, n_test=5)
    cfg = out / "wgs.toml"
    cfg.write_text(STRESS_TOML)
    ref = out / "reference"
    t0 = time.perf_counter()
    subprocess.run(wgs_command(ref, scene, cfg, False, checkpoint_every), check=True, stdout=subprocess.DEVNULL)
    total = time.perf_counter() - t0
    expected = outcome(ref)
    print(f"reference: {total:.1f} s, PSNR {expected['psnr']:.4f}", flush=True)
    trials = []
    for k in range(kills + 1):
        ws = out / f"trial{k:02d}"
        hammer = k == kills
        at = hammer_s if hammer else total * (k + 0.5) / kills
        stages, runs = [], 0
        while True:
            runs += 1
            resume = hammer or k % 2 == 0
            kill = hammer and runs < 40 or runs == 1  # the hammer gives up after 40 kills: then a clean finish
            rc, _ = run_until_killed(wgs_command(ws, scene, cfg, resume and runs > 1, checkpoint_every),
                                     at if kill else 3600)
            if rc is None:
                stages.append(running_stage(ws))
                continue
            if rc != 0:
                raise SystemExit(f"trial {k}: `wgs all` failed with exit status {rc} after a kill")
            break
        got = outcome(ws)
        diff = max_param_difference(ref, ws)
        trial = {"trial": k, "kill_after_s": round(at, 2), "killed_in": stages, "runs": runs,
                 "resume": hammer or k % 2 == 0, "same_metrics": got == expected, "max_param_diff": diff}
        trials.append(trial)
        print(json.dumps(trial), flush=True)
    summary = {"reference_seconds": round(total, 2), "kill_points": sum(len(t["killed_in"]) for t in trials),
               "trials": trials, "all_identical": all(t["same_metrics"] and t["max_param_diff"] == 0 for t in trials)}
    (out / "kill_loop.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m wgs.stress")
    sub = parser.add_subparsers(dest="what", required=True)
    k = sub.add_parser("kill-loop", help="SIGKILL `wgs all` at points spread over every stage, rerun, compare")
    k.add_argument("--kills", type=int, default=14)
    k.add_argument("--checkpoint-every", type=float, default=0.5)
    k.add_argument("--hammer-s", type=float, default=6.0, help="kill interval of the last trial")
    k.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(".numba_cache").resolve()))
    with tempfile.TemporaryDirectory() as tmp:
        summary = kill_loop(args.out or Path(tmp), args.kills, args.checkpoint_every, args.hammer_s)
    by_stage: dict[str, int] = {}
    for t in summary["trials"]:
        for s in t["killed_in"]:
            by_stage[s] = by_stage.get(s, 0) + 1
    print(f"kill points: {summary['kill_points']} ({', '.join(f'{s} {n}' for s, n in by_stage.items())}); "
          f"all results identical to the uninterrupted run: {summary['all_identical']}")
    if not summary["all_identical"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
