"""`wgs all`: the registry's stages in order (prepare -> coarse -> mask-data -> finetune -> repair
-> fine -> eval). Each stage is skipped when fresh; what a scene does not need is left out, with
one line each (`left_out`).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .io import read_json
from .progress import fmt, log, results
from .stages.registry import METHOD, REGISTRY, STAGE, UNASKED
from .workspace import Workspace

MANY_VIEWS = 12  # from this many training views on, diffusion repair is left out by default
REPAIR_STAGES = METHOD[METHOD.index("coarse") + 1 :]  # what a sparse-view scene adds to plain 3DGS


@dataclass
class StageOutcome:
    stage: str  # the stage's name (prepare, coarse, mask_data, ...)
    status: str  # ran | skipped (fresh) | left out
    seconds: float
    note: str = ""


def left_out(stage: str, info: dict[str, Any], force_repair: bool, asked: tuple[str, ...] = ()) -> str | None:
    """Why a scene does not need `stage` (one line for the log), or None when it runs; `asked`: the
    stages that run only on request and were asked for."""
    n_train = len(info["train_names"])
    if stage not in UNASKED and stage not in asked:
        return f"not asked for (--{STAGE[stage].command})"
    if stage in REPAIR_STAGES and n_train >= MANY_VIEWS and not force_repair:
        return f"{n_train} training views -> no diffusion repair (it is for sparse views; --force-repair runs it)"
    return None


def run_all(
    ctx,
    scene_dir: Path,
    preset: str | None,
    force: bool,
    force_repair: bool,
    overrides: dict[str, dict[str, Any]],
    asked: tuple[str, ...] = (),
    budget_s: float | None = None,
) -> list[StageOutcome]:
    """Run the registry's stages in order for the CLI context `ctx` (workspace, device, seed,
    config file), leaving out what the scene does not need and, of the stages that run only on
    request, those not in `asked`. After prepare it prints the estimate of what is left and, with
    `budget_s`, time-boxes the training stages so that the run ends within the budget; after the
    stopping rule's pilots (in the coarse stage, before its models), the estimate of the rest with the
    plateau they found."""
    from .estimate import RunTiming
    from .stages.registry import run_stage

    ws: Workspace = ctx.ws()
    device: torch.device = ctx.torch_device()
    cfgs = ctx.configs(preset, overrides)
    timing = RunTiming(device, cfgs, budget_s, asked)
    outcomes: list[StageOutcome] = []
    info: dict[str, Any] | None = None
    for stage in REGISTRY:
        if info is not None and (why := left_out(stage.name, info, force_repair, asked)) is not None:
            if (not outcomes or outcomes[-1].note != why) and stage.name in UNASKED:
                log(f"left out: {why}")
            outcomes.append(StageOutcome(stage.name, "left out", 0.0, why))
            continue
        final = "coarse" if info is not None and left_out("fine", info, force_repair) else "fine"
        env = ctx.env(
            device,
            scene_dir=scene_dir,
            final=final,
            working_size=timing,
            pilots_found=functools.partial(timing.after_pilots, ws, stage.name, cfgs=cfgs),
        )
        t0 = time.perf_counter()
        ran = run_stage(stage.name, ws, cfgs[stage.name], env, force)
        outcomes.append(StageOutcome(stage.name, "ran" if ran else "skipped (fresh)", time.perf_counter() - t0))
        if stage.name == "prepare":
            info = read_json(ws.output("prepare", "info"))
            if not info["has_masks"]:
                log("left out: no masks -> no visual hull, no mask loss, no random background")
            runs = tuple(s.name for s in REGISTRY if left_out(s.name, info, force_repair, asked) is None)
            cfgs = timing.after_prepare(ws, info, runs)
    return outcomes


def prepare_and_estimate(ctx, scene_dir: Path, preset: str | None, options: dict[str, Any], force: bool) -> None:
    """`wgs prepare`: import the scene at the working size chosen for the machine (unless the options
    set it) and print the estimate of the stages `wgs all` would run after it."""
    from .estimate import RunTiming
    from .stages.registry import run_stage

    ws: Workspace = ctx.ws()
    device: torch.device = ctx.torch_device()
    cfgs = ctx.configs(preset, {"prepare": options})
    timing = RunTiming(device, cfgs)
    run_stage("prepare", ws, cfgs["prepare"], ctx.env(device, scene_dir=scene_dir, working_size=timing), force)
    info = read_json(ws.output("prepare", "info"))
    timing.after_prepare(ws, info, tuple(s.name for s in REGISTRY if left_out(s.name, info, False) is None))


def print_summary(ws: Workspace, outcomes: list[StageOutcome]) -> None:
    from rich.table import Table

    table = Table(title=f"wgs all: {ws.root}")
    for col in ("stage", "this run", "time (s)", "stage wall time (s)"):
        table.add_column(col)
    for o in outcomes:
        m = ws.manifest(o.stage) or {}
        wt = m.get("wall_time_s")
        table.add_row(
            o.stage,
            o.status + (f" ({o.note})" if o.note else ""),
            f"{o.seconds:.1f}",
            "" if wt is None else f"{wt:.1f}",
        )
    results.print(table)
    res_path = ws.output("eval", "results")
    if res_path.is_file():
        r = read_json(res_path)
        c = r["coarse"]

        views = "test views" if r.get("views", "test") == "test" else "training views (no test views)"
        results.print(
            f"{views}: {r['num_views']}   PSNR {fmt(c['psnr'], 2)} -> {fmt(r['psnr'], 2)} dB   "
            f"SSIM {fmt(c['ssim'])} -> {fmt(r['ssim'])}   LPIPS {fmt(c['lpips'])} -> {fmt(r['lpips'])}   "
            f"(coarse -> final)"
        )
        results.print(f"report: {ws.output('eval', 'report')}")
