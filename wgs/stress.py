"""Slow robustness checks behind `make stress`.

    python -m wgs.stress kill-loop [--fractions 0.2,0.6,0.95] [--out DIR]

kill-loop: runs `wgs all` on a generated scene once without interruption (the reference), then
once per kill point: starts it in a fresh workspace, SIGKILLs it when a given stage has run for a
given fraction of its reference duration (every stage, several fractions, whatever the machine's
speed), reruns it (alternately with --resume and without) until it finishes, and compares the
results and the final model with the reference. A last trial kills every few seconds until the run
gets through. Prints one line per trial and writes kill_loop.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from .config import UNASKED
from .workspace import Workspace

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


def run_until_killed(cmd: list[str], ws: Path, stage: str | None, delay_s: float, timeout_s: float = 1800
                     ) -> int | None:
    """Start `cmd`; once `stage` has started (its upstream stage finished; None: never kill) wait
    `delay_s` more and SIGKILL it. Returns the exit status, or None when it was killed."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    try:
        if stage is not None:
            while not stage_started(ws, stage):
                if proc.poll() is not None or time.monotonic() - t0 > timeout_s:
                    break
                time.sleep(0.01)
            else:
                time.sleep(delay_s)
                if proc.poll() is None:
                    proc.send_signal(signal.SIGKILL)
                    proc.wait()
                    return None
        return proc.wait(timeout=timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def stage_started(ws: Path, stage: str) -> bool:
    """The stage before `stage` finished (for the first stage: the workspace lock exists)."""
    order = list(UNASKED)
    i = order.index(stage)
    if i == 0:
        return (ws / ".wgs.lock").exists()
    return Workspace(ws).manifest(order[i - 1]) is not None


def running_stage(ws: Path) -> str:
    """The first stage without a finished manifest: the one a kill interrupted."""
    w = Workspace(ws)
    for stage in UNASKED:
        if w.manifest(stage) is None:
            return stage
    return "after eval"


def outcome(ws: Path) -> dict[str, Any]:
    """What must not depend on interruptions: metrics and the final model's tensors."""
    res = json.loads(Workspace(ws).output("eval", "results").read_text())
    keep = {k: res[k] for k in ("psnr", "ssim", "num_gaussians")}
    keep["coarse"] = {k: res["coarse"][k] for k in ("psnr", "ssim", "num_gaussians")}
    return keep


def max_param_difference(a: Path, b: Path) -> float:
    ca = torch.load(Workspace(a).output("fine", "model"), weights_only=True)["splats"]
    cb = torch.load(Workspace(b).output("fine", "model"), weights_only=True)["splats"]
    if ca.keys() != cb.keys() or any(ca[k].shape != cb[k].shape for k in ca):
        return float("inf")
    return max(float((ca[k] - cb[k]).abs().max()) for k in ca)


def kill_loop(out: Path, fractions: list[float], checkpoint_every: float, hammer_s: float) -> dict[str, Any]:
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
    stage_s = {st: Workspace(ref).manifest(st)["wall_time_s"] for st in UNASKED}
    print(f"reference: {total:.1f} s, PSNR {expected['psnr']:.4f}; stage wall times (s): "
          + ", ".join(f"{k} {v:.1f}" for k, v in stage_s.items()), flush=True)
    # every stage, killed at fractions of its reference duration after it started; then a hammer trial
    plan = [(st, f) for st in UNASKED for f in fractions] + [("hammer", hammer_s)]
    trials = []
    for k, (target, frac) in enumerate(plan):
        ws = out / f"trial{k:02d}"
        hammer = target == "hammer"
        resume = hammer or k % 2 == 0
        killed: list[str] = []
        runs = 0
        while True:
            runs += 1
            cmd = wgs_command(ws, scene, cfg, resume and runs > 1, checkpoint_every)
            if hammer and runs < 40:  # killed every hammer_s seconds after start; a clean finish after 40 kills
                stage, delay = list(UNASKED)[0], frac
            elif runs == 1:
                stage, delay = target, frac * stage_s[target]
            else:
                stage, delay = None, 0.0
            rc = run_until_killed(cmd, ws, stage, delay)
            if rc is None:
                killed.append(running_stage(ws))
                continue
            if rc != 0:
                raise SystemExit(f"trial {k}: `wgs all` failed with exit status {rc} after a kill")
            break
        got = outcome(ws)
        diff = max_param_difference(ref, ws)
        trial = {"trial": k, "target": target, "kill_at": round(frac, 2), "killed_in": killed, "runs": runs,
                 "resume": resume, "same_metrics": got == expected, "max_param_diff": diff}
        trials.append(trial)
        print(json.dumps(trial), flush=True)
        shutil.rmtree(ws, ignore_errors=True)
    summary = {"reference_seconds": round(total, 2), "stage_seconds": stage_s,
               "kill_points": sum(len(t["killed_in"]) for t in trials), "trials": trials,
               "all_identical": all(t["same_metrics"] and t["max_param_diff"] == 0 for t in trials)}
    (out / "kill_loop.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m wgs.stress")
    sub = parser.add_subparsers(dest="what", required=True)
    k = sub.add_parser("kill-loop", help="SIGKILL `wgs all` at points spread over every stage, rerun, compare")
    k.add_argument("--fractions", default="0.2,0.6,0.95",
                   help="kill points per stage, as fractions of its reference duration")
    k.add_argument("--checkpoint-every", type=float, default=0.5)
    k.add_argument("--hammer-s", type=float, default=6.0, help="kill interval of the last trial")
    k.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(".numba_cache").resolve()))
    with tempfile.TemporaryDirectory() as tmp:
        fractions = [float(x) for x in args.fractions.split(",")]
        summary = kill_loop(args.out or Path(tmp), fractions, args.checkpoint_every, args.hammer_s)
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
