"""Slow robustness checks behind `make stress`.

    python -m tools.stress kill-loop [--fractions 0.2,0.6,0.95] [--out DIR]
    python -m tools.stress signal-loop [--moments 10] [--seed 0] [--out DIR]

kill-loop: runs `wgs all` on a generated scene once without interruption (the reference), then
once per kill point: starts it in a fresh workspace, SIGKILLs it when a given stage has run for a
given fraction of its reference duration (every stage, several fractions, whatever the machine's
speed), reruns it (alternately with --resume and without) until it finishes, and compares the
results and the final model with the reference. A last trial kills every few seconds until the run
gets through. Prints one line per trial and writes kill_loop.json.

signal-loop: the same reference, then SIGINT, SIGTERM and SIGUSR1 (a scheduler's stop signals), each
sent at `--moments` random moments of the run: every stopped run must print one line on stderr,
no stack trace, and exit with 128 + the signal's number; `wgs --resume all` then finishes it, with
results and a final model identical to the reference's. Writes signal_loop.json.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import click
import torch

from wgs.stages.registry import UNASKED
from wgs.workspace import Workspace

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
    return [
        sys.executable,
        "-m",
        "wgs",
        "-q",
        "--config",
        str(cfg),
        "--checkpoint-every",
        str(checkpoint_every),
        *(["--resume"] if resume else []),
        "-w",
        str(ws),
        "all",
        str(scene),
    ]


def run_until_killed(
    cmd: list[str], ws: Path, stage: str | None, delay_s: float, timeout_s: float = 1800
) -> int | None:
    """Start `cmd`; once `stage` has started (its upstream stage finished; None: never kill) wait
    `delay_s` more and SIGKILL it. Returns the exit status, or None when it was killed."""
    rc, _, sent = run_and_signal(cmd, ws, stage, delay_s, signal.SIGKILL, timeout_s)
    return None if sent else rc


def run_and_signal(
    cmd: list[str], ws: Path, stage: str | None, delay_s: float, sig: int, timeout_s: float = 1800
) -> tuple[int, str, bool]:
    """Start `cmd`; once `stage` has started (its upstream stage finished; None: never) wait `delay_s`
    more and send `sig`. Returns the exit status, stderr, and whether the signal was sent."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0, sent = time.monotonic(), False
    try:
        if stage is not None:
            while not stage_started(ws, stage):
                if proc.poll() is not None or time.monotonic() - t0 > timeout_s:
                    break
                time.sleep(0.01)
            else:
                time.sleep(delay_s)
                if proc.poll() is None:
                    proc.send_signal(sig)
                    sent = True
        _, err = proc.communicate(timeout=timeout_s)
        return proc.returncode, err, sent
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


def reference_run(out: Path, checkpoint_every: float) -> tuple[Path, Path, Path, float, dict[str, float]]:
    """The generated scene, the config, and `wgs all` on it uninterrupted: (scene, config, reference
    workspace, its wall time, each stage's wall time)."""
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
    stage_s = {st: Workspace(ref).finished(st)["wall_time_s"] for st in UNASKED}
    print(
        f"reference: {total:.1f} s, PSNR {outcome(ref)['psnr']:.4f}; stage wall times (s): "
        + ", ".join(f"{k} {v:.1f}" for k, v in stage_s.items()),
        flush=True,
    )
    return scene, cfg, ref, total, stage_s


# what a stopped run may print instead of its one line: a Python or a native (glog) stack trace
STACK_MARKERS = ("Traceback", "stack trace", "*** Aborted at")


def signal_loop(out: Path, moments: int, seed: int, checkpoint_every: float) -> dict[str, Any]:
    """SIGINT, SIGTERM and SIGUSR1 at `moments` random moments each (see the module's docstring)."""
    import random

    scene, cfg, ref, total, _ = reference_run(out, checkpoint_every)
    expected = outcome(ref)
    rnd = random.Random(seed)
    trials = []
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1):
        for m in range(moments):
            ws = out / f"{sig.name}_{m:02d}"
            at = rnd.uniform(0.02, 0.98) * total
            rc, err, sent = run_and_signal(
                wgs_command(ws, scene, cfg, False, checkpoint_every), ws, list(UNASKED)[0], at, sig
            )
            lines = [ln for ln in err.splitlines() if ln.strip()]
            stopped_in = running_stage(ws)
            rc2, err2, _ = run_and_signal(wgs_command(ws, scene, cfg, True, checkpoint_every), ws, None, 0.0, sig)
            trial = {
                "signal": sig.name,
                "at_s": round(at, 2),
                "stopped_in": stopped_in,
                "exit": rc,
                "expected_exit": 128 + sig if sent and stopped_in != "after eval" else 0,
                "stderr_lines": len(lines),
                "stack_trace": any(mark in err for mark in STACK_MARKERS),
                "resumed_exit": rc2,
                "same_metrics": rc2 == 0 and outcome(ws) == expected,
                "max_param_diff": max_param_difference(ref, ws) if rc2 == 0 else float("inf"),
            }
            trial["ok"] = (
                trial["exit"] == trial["expected_exit"]
                and (rc == 0 or len(lines) == 1)
                and not trial["stack_trace"]
                and trial["same_metrics"]
                and trial["max_param_diff"] == 0
            )
            if not trial["ok"]:
                trial["stderr"] = err[-2000:] + err2[-1000:]
            trials.append(trial)
            print(json.dumps(trial), flush=True)
            shutil.rmtree(ws, ignore_errors=True)
    summary = {"reference_seconds": round(total, 2), "trials": trials, "all_ok": all(t["ok"] for t in trials)}
    (out / "signal_loop.json").write_text(json.dumps(summary, indent=2))
    return summary


def kill_loop(out: Path, fractions: list[float], checkpoint_every: float, hammer_s: float) -> dict[str, Any]:
    scene, cfg, ref, total, stage_s = reference_run(out, checkpoint_every)
    expected = outcome(ref)
    # every stage, killed at fractions of its reference duration after it started; then a hammer trial
    plan = [(st, f) for st in UNASKED for f in fractions] + [("hammer", hammer_s)]
    trials: list[dict[str, Any]] = []
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
        trial = {
            "trial": k,
            "target": target,
            "kill_at": round(frac, 2),
            "killed_in": killed,
            "runs": runs,
            "resume": resume,
            "same_metrics": got == expected,
            "max_param_diff": diff,
        }
        trials.append(trial)
        print(json.dumps(trial), flush=True)
        shutil.rmtree(ws, ignore_errors=True)
    summary = {
        "reference_seconds": round(total, 2),
        "stage_seconds": stage_s,
        "kill_points": sum(len(t["killed_in"]) for t in trials),
        "trials": trials,
        "all_identical": all(t["same_metrics"] and t["max_param_diff"] == 0 for t in trials),
    }
    (out / "kill_loop.json").write_text(json.dumps(summary, indent=2))
    return summary


CHECKPOINT_EVERY = click.option(
    "--checkpoint-every", default=0.5, show_default=True, help="seconds between training snapshots"
)
OUT = click.option(
    "--out", type=click.Path(path_type=Path), default=None, help="keep the runs here (default: a temporary folder)"
)


@click.group()
def main() -> None:
    """Interrupt `wgs all` and check that the resumed run ends as the uninterrupted one (the numba
    kernels from numba's cache, where the set-up compiled them)."""


@main.command("kill-loop")
@click.option(
    "--fractions",
    default="0.2,0.6,0.95",
    show_default=True,
    help="kill points per stage, as fractions of its reference duration",
)
@CHECKPOINT_EVERY
@click.option("--hammer-s", default=6.0, show_default=True, help="kill interval of the last trial")
@OUT
def kill_loop_command(fractions: str, checkpoint_every: float, hammer_s: float, out: Path | None) -> None:
    """SIGKILL `wgs all` at points spread over every stage, rerun, compare."""
    with tempfile.TemporaryDirectory() as tmp:
        points = [float(x) for x in fractions.split(",")]
        summary = kill_loop(out or Path(tmp), points, checkpoint_every, hammer_s)
    by_stage: dict[str, int] = {}
    for t in summary["trials"]:
        for s in t["killed_in"]:
            by_stage[s] = by_stage.get(s, 0) + 1
    print(
        f"kill points: {summary['kill_points']} ({', '.join(f'{s} {n}' for s, n in by_stage.items())}); "
        f"all results identical to the uninterrupted run: {summary['all_identical']}"
    )
    if not summary["all_identical"]:
        sys.exit(1)


@main.command("signal-loop")
@click.option("--moments", default=10, show_default=True, help="random moments per signal")
@click.option("--seed", default=0, show_default=True, help="seed of the moments")
@CHECKPOINT_EVERY
@OUT
def signal_loop_command(moments: int, seed: int, checkpoint_every: float, out: Path | None) -> None:
    """SIGINT, SIGTERM and SIGUSR1 at random moments, --resume, compare."""
    with tempfile.TemporaryDirectory() as tmp:
        summary = signal_loop(out or Path(tmp), moments, seed, checkpoint_every)
    bad = [t for t in summary["trials"] if not t["ok"]]
    print(f"{len(summary['trials'])} stops, {len(bad)} not as expected")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
