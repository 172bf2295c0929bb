"""`wgs all`: prepare -> coarse -> mask-data -> finetune -> repair -> fine -> eval.

Each stage is skipped when fresh; what a scene does not need is left out, with one line each.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .config import METHOD, RESULTS
from .io import read_json
from .progress import log, results
from .workspace import Workspace

MANY_VIEWS = 12  # from this many training views on, diffusion repair is left out by default
REPAIR_STAGES = METHOD[METHOD.index("coarse") + 1:]  # what a sparse-view scene adds to plain 3DGS


@dataclass
class StageOutcome:
    stage: str
    status: str  # ran | skipped (fresh) | left out
    seconds: float
    note: str = ""


def run_all(ctx, scene_dir: Path, preset: str | None, force: bool, force_repair: bool,
            overrides: dict[str, dict[str, Any]]) -> list[StageOutcome]:
    """Run the whole pipeline for the CLI context `ctx` (workspace, device, seed, config file)."""
    from .stages.s0_prepare import run_prepare
    from .stages.s1_coarse import run_coarse
    from .stages.s2_mask_data import run_mask_data
    from .stages.s3_finetune import run_finetune
    from .stages.s4_repair import run_repair
    from .stages.s5_fine import run_fine
    from .stages.s6_eval import run_eval

    ws: Workspace = ctx.ws()
    device: torch.device = ctx.torch_device()
    outcomes: list[StageOutcome] = []

    def step(stage: str, fn, *args, **kw) -> None:
        t0 = time.perf_counter()
        ran = fn(*args, **kw)
        outcomes.append(StageOutcome(stage, "ran" if ran else "skipped (fresh)", time.perf_counter() - t0))

    def cfg(stage: str):
        return ctx.config(stage, preset, **overrides.get(stage, {}))

    step("prepare", run_prepare, ws, scene_dir, cfg("prepare"), force=force)
    info = read_json(ws.stage_dir("scene") / "scene.json")
    n_train, n_test = len(info["train_names"]), len(info["test_names"])
    if not info["has_masks"]:
        log("left out: no masks -> no visual hull, no mask loss, no random background")
    step("coarse", run_coarse, ws, cfg("coarse"), device, ctx.seed, force=force)
    repair = n_train < MANY_VIEWS or force_repair
    if repair:
        step("mask_data", run_mask_data, ws, cfg("mask_data"), device, ctx.seed, force=force)
        step("finetune", run_finetune, ws, cfg("finetune"), device, ctx.seed, force=force)
        step("repair", run_repair, ws, cfg("repair"), device, ctx.seed, force=force)
        step("fine", run_fine, ws, cfg("fine"), device, ctx.seed, force=force)
    else:
        log(f"left out: {n_train} training views -> no diffusion repair (it is for sparse views; "
            "--force-repair runs it)")
        outcomes += [StageOutcome(s, "left out", 0.0, f"{n_train} views") for s in REPAIR_STAGES]
    if n_test:
        step("eval", run_eval, ws, cfg("eval"), device, force=force, final="fine" if repair else "coarse",
             seed=ctx.seed)
    else:
        log("left out: no test views -> no eval, no report numbers")
        outcomes.append(StageOutcome("eval", "left out", 0.0, "no test views"))
    return outcomes


def print_summary(ws: Workspace, outcomes: list[StageOutcome]) -> None:
    from rich.table import Table

    table = Table(title=f"wgs all: {ws.root}")
    for col in ("stage", "this run", "time (s)", "stage wall time (s)"):
        table.add_column(col)
    for o in outcomes:
        m = ws.manifest("scene" if o.stage == "prepare" else o.stage) or {}
        wt = m.get("wall_time_s")
        table.add_row(o.stage, o.status + (f" ({o.note})" if o.note else ""), f"{o.seconds:.1f}",
                      "" if wt is None else f"{wt:.1f}")
    results.print(table)
    res_path = ws.stage_dir("eval") / RESULTS
    if res_path.is_file():
        r = read_json(res_path)
        c = r["coarse"]

        def f(v, nd=3):
            return "n/a" if v is None else f"{v:.{nd}f}"

        results.print(f"test views: {r['num_views']}   PSNR {f(c['psnr'], 2)} -> {f(r['psnr'], 2)} dB   "
                      f"SSIM {f(c['ssim'])} -> {f(r['ssim'])}   LPIPS {f(c['lpips'])} -> {f(r['lpips'])}   "
                      f"(coarse -> final)")
        results.print(f"report: {ws.stage_dir('eval') / 'report.md'}")
