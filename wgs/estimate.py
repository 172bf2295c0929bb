"""How long `wgs all` takes on this machine, the working size chosen for it, and the plan that fits
a time budget.

A calibration of about 3 s times, on this machine and device, a training view's core at two sizes
(the rasterizer's forward + backward on a synthetic cloud, and the photometric loss's), a training
step of the repair network D and its forward pass.
A stage's time is then its work in those units (iterations, views, pixels, D steps and forwards)
times a factor measured on whole runs, plus a fixed part in D-step units: each stage's cost model
(`Stage.cost`, in its settings module) says how, from the pieces in `wgs.cost` (docs/speed.md
"Working size, estimate and budget"). The estimate is printed before training and kept in
`WS/run.json`; the report puts it beside the stages' actual times.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import re
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from .config import as_dict
from .cost import (
    CPU_TARGET_S,
    D_STEP_BATCH,
    D_STEP_CHANNELS,
    D_STEP_CROP,
    FIT_MASK_SHARE,
    GPU_MAX_SIZE,
    Calibration,
    SceneFacts,
    StageCost,
    plateau_from_hull,
    time_boxed,
)
from .errors import InputError
from .gaussians.trainer import TrainConfig
from .io import atomic_write_json
from .progress import log
from .scene.prepare import downscale_for
from .stages.registry import REGISTRY, UNASKED
from .workspace import UPSTREAM, Workspace, fingerprint

CALIBRATION_SIDES = (128, 256)  # square views the rasterizer is timed at
CALIBRATION_GAUSSIANS = 8000  # about a 4-view model's size at 200 px
MIN_SIZE = 96  # no working size below this long side (px), whatever the budget
# the training stages' share of a budget is time-boxed with iteration caps this many times the
# planned rate, so that the time, not the caps, ends them even where the calibration was slow
# (1.5 let a calibration twice too slow end ethiopianHead's 20-minute budget at 0.80 of it)
HEADROOM = 3.0
# a new calibration is made once the newest held is this old (a test suite's many small runs, a batch
# of scenes reuse it); each is held, on the same machine, device, thread count and versions, in
# $WGS_CACHE (default ~/.cache/wgs)
CALIBRATION_MAX_AGE_S = 3600.0
# the estimate times the machine by the median of its calibrations of the last day, the newest
# CALIBRATION_HISTORY: a shared machine's speed drifts by more than the estimate's tolerance within
# hours, and one calibration made at a quick or slow moment would move every estimate of the next hour
CALIBRATION_HISTORY = 5
CALIBRATION_HISTORY_S = 86400.0
# a held calibration is left out where the rasterizer's probe (`probe_s`) now runs this many times as
# fast as when it was made: it was made on a busier machine (another run's processes), and would
# lengthen every estimate
BUSIER_RATIO = 1.25
PROBE_SIDE = CALIBRATION_SIDES[0]
FIRST = REGISTRY[0].name  # the stage that reads the scene; the estimate is made after it
# the stages a budget shares out unless told which: those after the first that run unasked
AFTER_FIRST = tuple(s.name for s in REGISTRY[1:] if not s.on_request)
TRAIN_STAGES = tuple(s.name for s in REGISTRY if issubclass(s.settings, TrainConfig))  # a time box caps them


def _affine(sides: tuple[int, int], seconds: tuple[float, float]) -> tuple[float, float]:
    (a, b), (ta, tb) = (s * s for s in sides), seconds
    slope = max((tb - ta) / (b - a), 0.0)
    return max(ta - slope * a, 0.0), slope


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def calibrate(device: torch.device) -> Calibration:
    """Time the rasterizer and D on `device` (about 4 s on a 2-core CPU); the global random state
    is left as it was."""
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        return _calibrate(device)


def _calibrate(device: torch.device) -> Calibration:
    from .gaussians.render import pick_backend
    from .gaussians.synthetic import time_backend
    from .models.ll_denoiser import LLDenoiser, LLDenoiserConfig
    from .threads import configured_count

    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(0)
    # the sizes interleaved, so that a passing load slows both alike rather than one (which tilts the fit)
    best = {s: math.inf for s in CALIBRATION_SIDES}
    for _ in range(5):
        for s in CALIBRATION_SIDES:
            timed = time_backend(pick_backend(device), s, CALIBRATION_GAUSSIANS, 2, device=device)
            best[s] = min(best[s], timed["forward_backward"]["min_s"])
    small, large = (best[s] + _loss_s(s, device, gen) for s in CALIBRATION_SIDES)
    raster = _affine(CALIBRATION_SIDES, (small, large))
    d = LLDenoiser(LLDenoiserConfig(3, D_STEP_CHANNELS)).to(device)
    opt = torch.optim.Adam(d.parameters(), 1e-4)
    x = torch.randn(D_STEP_BATCH, 3, D_STEP_CROP, D_STEP_CROP, generator=gen).to(device)
    t = torch.full((D_STEP_BATCH,), 500, device=device)
    steps = []
    for i in range(6):  # the first warms up
        t1 = time.perf_counter()
        d(x, t, x).square().mean().backward()
        opt.step()
        opt.zero_grad()
        _sync(device)
        if i:
            steps.append(time.perf_counter() - t1)
    side = CALIBRATION_SIDES[0]
    y = torch.randn(1, 3, side, side, generator=gen).to(device)
    forwards = []
    with torch.no_grad():
        for i in range(5):
            t1 = time.perf_counter()
            d(y, t[:1], y)
            _sync(device)
            if i:
                forwards.append(time.perf_counter() - t1)
    return Calibration(
        raster, min(steps), min(forwards) / (side * side), configured_count(), str(device), time.perf_counter() - t0
    )


def _loss_s(side: int, device: torch.device, gen: torch.Generator, repeats: int = 6) -> float:
    """Seconds of the trainer's photometric loss (L1 + SSIM), forward and backward, on a `side`² view."""
    from .gaussians.trainer import photometric_loss

    target = torch.rand(side, side, 3, generator=gen).to(device)
    times = []
    for i in range(repeats + 1):
        render = torch.rand(side, side, 3, generator=gen).to(device).requires_grad_(True)
        t1 = time.perf_counter()
        photometric_loss(render, target, 0.2).backward()
        _sync(device)
        if i:
            times.append(time.perf_counter() - t1)
    return min(times)


def cache_dir() -> Path:
    return Path(os.environ.get("WGS_CACHE") or Path.home() / ".cache" / "wgs")


def machine_key(device: torch.device) -> str:
    from . import __version__
    from .threads import configured_count

    return (
        f"{platform.node()}|{platform.machine()}|{device}|{configured_count()} threads|torch {torch.__version__}|"
        f"wgs {__version__}"
    )


def probe_s(device: torch.device) -> float:
    """Seconds of the rasterizer's forward + backward on the calibration's small view, the least of
    3 (about 0.1 s on a 2-core CPU): how busy the machine is now, against a cached calibration."""
    from .gaussians.render import pick_backend
    from .gaussians.synthetic import time_backend

    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        timed = time_backend(pick_backend(device), PROBE_SIDE, CALIBRATION_GAUSSIANS, 3, device=device)
    return float(timed["forward_backward"]["min_s"])


def typical(cals: list[Calibration]) -> Calibration:
    """The median of `cals`' timings, each on its own (threads, device and `seconds` the last one's)."""
    med = statistics.median
    return dataclasses.replace(
        cals[-1],
        raster=(med(c.raster[0] for c in cals), med(c.raster[1] for c in cals)),
        d_step_s=med(c.d_step_s for c in cals),
        d_forward_s_per_pixel=med(c.d_forward_s_per_pixel for c in cals),
    )


def _held(entries: Any, now: float) -> list[dict]:
    """The well-formed calibration records of the last CALIBRATION_HISTORY_S, oldest first (one
    record alone, as an older cache held it, counts as a list of one)."""
    entries = [entries] if isinstance(entries, dict) else entries if isinstance(entries, list) else []
    out: list[dict[str, Any]] = []
    for e in entries:
        try:
            cal = Calibration(**{**e["calibration"], "raster": tuple(e["calibration"]["raster"])})
            if 0 <= now - float(e["made"]) <= CALIBRATION_HISTORY_S:
                out.append({"made": float(e["made"]), "probe_s": float(e["probe_s"]), "calibration": cal})
        except (KeyError, TypeError, ValueError):
            continue
    return sorted(out, key=lambda e: e["made"])[-CALIBRATION_HISTORY:]


def cached_calibration(device: torch.device, now: float | None = None) -> Calibration:
    """The `typical` of this machine's calibrations held (`_held`), after a new one (`calibrate`) where
    the newest is older than CALIBRATION_MAX_AGE_S. Those made on a busier machine (the probe now runs
    BUSIER_RATIO times as fast as it did then) are left out, and forgotten once a new one is made."""
    path, key, now = cache_dir() / "calibration.json", machine_key(device), time.time() if now is None else now
    probe = probe_s(device)
    try:
        cache = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        cache = {}
    cache = cache if isinstance(cache, dict) else {}
    held = _held(cache.get(key), now)
    idle = [e for e in held if probe * BUSIER_RATIO >= e["probe_s"]]
    if idle and now - idle[-1]["made"] <= CALIBRATION_MAX_AGE_S:
        return typical([e["calibration"] for e in idle])
    if held and now - held[-1]["made"] <= CALIBRATION_MAX_AGE_S:
        log(
            f"calibration: the cached one was made on a busier machine (its probe {held[-1]['probe_s'] * 1e3:.1f} ms,"
            f" now {probe * 1e3:.1f} ms); timing again"
        )
    cal = calibrate(device)
    idle = [*idle, {"made": now, "probe_s": min(probe, probe_s(device)), "calibration": cal}][-CALIBRATION_HISTORY:]
    try:
        others = {k: v for k, v in cache.items() if k != key and _held(v, now)}
        records = [{**e, "calibration": dataclasses.asdict(e["calibration"])} for e in idle]
        atomic_write_json(path, {**others, key: records})
    except OSError:
        pass  # a read-only home: calibrate every run
    return typical([e["calibration"] for e in idle])


def costs(cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts) -> dict[str, tuple[StageCost, float]]:
    """Each stage's cost model (`Stage.cost`) and modelled wall time in seconds, for the stage
    configs `cfgs` (stage name -> config) on a scene with `facts`."""
    out: dict[str, tuple[StageCost, float]] = {}
    for stage in REGISTRY:
        cost = stage.cost(cal, cfgs, facts, {name: seconds for name, (_, seconds) in out.items()})
        out[stage.name] = cost, cost.seconds(cal, getattr(cfgs[stage.name], "max_seconds", None))
    return out


def stage_seconds(cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts) -> dict[str, float]:
    """Modelled wall time of each stage (stage name -> seconds) for the stage configs `cfgs`
    (stage name -> config) on a scene with `facts`."""
    return {name: round(seconds, 1) for name, (_, seconds) in costs(cal, cfgs, facts).items()}


def per_stage(model: dict[str, float], tables: tuple[str, ...]) -> dict[str, float | None]:
    """The modelled seconds of each of `tables`, None (unknown) for a table the cost model lacks."""
    return {t: model.get(t) for t in tables}


def choose_downscale(
    cal: Calibration,
    cfgs: dict[str, Any],
    facts: SceneFacts,
    target_s: float | None,
    runs: tuple[str, ...] = UNASKED,
) -> tuple[int, float | None]:
    """The working size for the machine: on a GPU a long side of at most GPU_MAX_SIZE; else (or
    within a budget) the largest integer downscale of the photos (`facts` at full size) at which
    the modelled `wgs all` takes at most `target_s`, but not below MIN_SIZE. Returns (downscale,
    modelled seconds at it, or None on a GPU without a target); `runs`: the config tables of the
    stages that run."""
    first = downscale_for(facts.width, facts.height, GPU_MAX_SIZE) if cal.device != "cpu" else 1
    if target_s is None:
        return first, None
    last = max(first, max(facts.width, facts.height) // MIN_SIZE)  # the last long side >= MIN_SIZE
    k, total = first, math.inf
    for k in range(first, last + 1):
        w, h = facts.width // k, facts.height // k
        model = stage_seconds(cal, cfgs, dataclasses.replace(facts, width=w, height=h))
        total = sum(v or 0.0 for v in per_stage(model, runs).values())
        if total <= target_s:
            break
    return k, total


def budget_plan(
    cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts, left_s: float, runs: tuple[str, ...] = AFTER_FIRST
) -> dict[str, Any]:
    """The training stages in `runs` time-boxed so that the stages in `runs` take `left_s` seconds:
    what the others are modelled to take is set aside, the rest shared among the training stages
    (those whose cost model has training loops) in proportion to their modelled times. Returns
    {"stages": name -> time-boxed config, "seconds": name -> planned seconds}. The first stage has
    run when the plan is made: it is left out."""
    runs = tuple(t for t in runs if t != FIRST)
    modelled = costs(cal, cfgs, facts)
    model = {t: round(seconds, 1) for t, (_, seconds) in modelled.items()}
    fixed_s = {t: cost.fixed_steps * cal.d_step_s for t, (cost, _) in modelled.items()}
    followers = [s for s in REGISTRY if s.trains_for and s.name in runs]
    for s in followers:  # it trains as long again as the stages it follows take: they get half of the rest
        after = sum(model[t] for t in runs if t not in s.trains_for and t != s.name)
        left_s = (left_s - after - fixed_s[s.name]) / 2 + after
    trained = [s.name for s in REGISTRY if s.name in runs and modelled[s.name][0].loops]
    others = [s.name for s in REGISTRY if s.name in runs and s.name not in trained and s not in followers]
    train = max(left_s - sum(model[t] for t in others) - sum(fixed_s[t] for t in trained), 1.0)
    total = sum(c.loops * c.loop_s * c.factor for c, _ in (modelled[t] for t in trained))
    stages, seconds = {}, {}
    for table in trained:
        cost = modelled[table][0]
        share = train * cost.loops * cost.loop_s * cost.factor / total
        stages[table] = time_boxed(cfgs[table], share / cost.loops, cost.loop_s * cost.factor, HEADROOM)
        seconds[table] = round(fixed_s[table] + share, 1)
    for table in others:
        seconds[table] = model[table]
    for s in followers:
        seconds[s.name] = round(fixed_s[s.name] + sum(seconds[t] for t in s.trains_for if t in seconds), 1)
    return {"stages": stages, "seconds": seconds}


_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(s|sec|m|min|h)?\s*$")


def parse_duration(text: str) -> float:
    """'10m', '90s', '1.5h', '600s' -> seconds; a bare number is minutes."""
    m = _DURATION.match(text)
    if m is None or float(m.group(1)) <= 0:
        raise InputError(f"a budget is a positive duration such as 10m, 90s or 1h, got {text!r}")
    return float(m.group(1)) * {"s": 1, "sec": 1, "m": 60, "min": 60, "h": 3600, None: 60}[m.group(2)]


def minutes(seconds: float) -> str:
    return f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"


def estimate_line(model: dict[str, float | None], what: str = "estimate") -> str:
    """`estimate: about 9 min on this machine (coarse 4 min, ...)`, the stages in `model`'s order;
    a stage without a cost model (None) is named as unknown and left out of the sum."""
    parts = ", ".join(f"{t.replace('_', '-')} {'unknown' if s is None else minutes(s)}" for t, s in model.items())
    unknown = [t.replace("_", "-") for t, s in model.items() if s is None]
    total = minutes(sum(s for s in model.values() if s is not None))
    more = f" and {', '.join(unknown)} unknown (no cost model)" if unknown else ""
    return f"{what}: about {total} on this machine{more} ({parts})"


class RunTiming:
    """One run's calibration (made once, when first needed), the working size it chooses for the
    machine or the budget, and, after prepare, the estimate of the stages still to run and the
    budget's plan, recorded in the workspace (`Workspace.run_record`)."""

    def __init__(
        self, device: torch.device, cfgs: dict[str, Any], budget_s: float | None = None, asked: tuple[str, ...] = ()
    ):
        """`asked`: the stages that run only on request and were asked for (`wgs all --baseline`)."""
        self.device, self.cfgs, self.budget_s = device, cfgs, budget_s
        self.runs = UNASKED + asked
        self.started = time.perf_counter()
        self._cal: Calibration | None = None
        self.facts: SceneFacts | None = None  # the scene's, once prepare ran
        self.pending: tuple[str, ...] = ()  # the stages estimated after prepare
        self.key = f"budget {budget_s:g} s" if budget_s else f"machine ({device.type})"

    def calibration(self) -> Calibration:
        if self._cal is None:
            self._cal = cached_calibration(self.device)
        return self._cal

    def __call__(
        self, width: int, height: int, n_train: int, n_test: int, has_masks: bool, mask_share: float | None = None
    ) -> tuple[int, str]:
        """The working size (`stages.stage.WorkingSize`)."""
        if self.device.type != "cpu" and not self.budget_s:
            k = downscale_for(width, height, GPU_MAX_SIZE)
            return k, (
                f"working size: {width // k}x{height // k} (the photos' {width}x{height} / {k}): a long side "
                f"of at most {GPU_MAX_SIZE} px on a GPU; --max-size or --downscale set it"
            )
        cal = self.calibration()
        target = self.budget_s or CPU_TARGET_S
        facts = SceneFacts(
            width,
            height,
            n_train,
            n_test,
            full_pixels=width * height,
            has_masks=has_masks,
            mask_share=FIT_MASK_SHARE if mask_share is None else mask_share,
        )
        k, modelled = choose_downscale(cal, self.cfgs, facts, target, self.runs)
        total = modelled if modelled is not None else math.inf  # a target gives a time
        limit = f"the budget of {minutes(target)}" if self.budget_s else f"about {minutes(target)}"
        if k == 1 and total <= target:
            why = f"the photos' own size: wgs all is modelled to take {minutes(total)} at it"
        elif total <= target:
            why = (
                f"the photos' {width}x{height} / {k}, the largest size at which wgs all is modelled to take "
                f"{limit} ({minutes(total)})"
            )
        else:
            why = (
                f"the photos' {width}x{height} / {k}, the smallest allowed (a long side of at least {MIN_SIZE} px): "
                f"wgs all is modelled to take {minutes(total)} at it, over {limit}"
            )
        cover = f"; the object covers {100 * mask_share:.0f} % of the photos" if mask_share is not None else ""
        return k, (
            f"working size: {width // k}x{height // k} ({why}{cover}; {cal.device}, {cal.threads} threads); "
            "--max-size or --downscale set it"
        )

    def after_prepare(self, ws: Workspace, info: dict[str, Any], runs: tuple[str, ...]) -> dict[str, Any]:
        """Print the estimate of the stages in `runs` (config tables) that are not up to date and,
        with a budget, time-box the training stages so that the run ends within it. Returns the
        configs to run with (`cfgs` with the budget's plan)."""
        res = info["resolution"]
        w, h = res if isinstance(res[0], int) else res[0]
        facts = SceneFacts(
            w,
            h,
            len(info["train_names"]),
            len(info["test_names"]),
            has_masks=info["has_masks"],
            posed_by_wgs=info.get("format") == "photos",
            mask_share=(info.get("masks") or {}).get("training_share", FIT_MASK_SHARE),
            expected_plateau=plateau_from_hull(hull_loo_iou(info)),
        )
        held = ws.run_record()
        cfgs = dict(self.cfgs)
        plan: dict[str, Any] | None = None
        if self.budget_s:
            reuse = (
                held.get("budget_s") == self.budget_s
                and held.get("plan")
                and all(_fresh(ws, t, cfgs[t], held["plan"]["stages"].get(t)) for t in TRAIN_STAGES if t in runs)
            )
            if reuse:  # a rerun with the same budget keeps its time-boxes: the stages stay up to date
                plan = held["plan"]
            else:
                left = self.budget_s - (time.perf_counter() - self.started) - END_S
                made = budget_plan(self.calibration(), cfgs, facts, left, runs)
                plan = {"stages": {t: _boxed_fields(c) for t, c in made["stages"].items()}, "seconds": made["seconds"]}
            for t, fields in plan["stages"].items():
                cfgs[t] = dataclasses.replace(cfgs[t], **fields)
            log(
                f"budget: {minutes(self.budget_s)} -> "
                + ", ".join(f"{t.replace('_', '-')} {minutes(s)}" for t, s in plan["seconds"].items() if t in runs)
                + " (the training stages time-boxed)"
            )
        pending = _pending(ws, runs, cfgs)
        self.facts, self.pending = facts, pending
        record: dict[str, Any] = {"budget_s": self.budget_s, "plan": plan}
        if pending:
            cal = self.calibration()
            model = stage_seconds(cal, cfgs, facts)
            estimate = per_stage(model, pending)
            log(estimate_line(estimate))
            record.update(
                estimate=estimate,
                calibration=dataclasses.asdict(cal),
                scene={
                    "width": w,
                    "height": h,
                    "train": facts.n_train,
                    "test": facts.n_test,
                    "has_masks": facts.has_masks,
                    "mask_share": facts.mask_share,
                    "expected_plateau": facts.expected_plateau,
                },
            )
        elif held.get("estimate"):
            record.update({k: held[k] for k in ("estimate", "calibration", "scene") if k in held})
        ws.write_run_record(record)
        return cfgs

    def after_pilots(self, ws: Workspace, name: str, stop: dict[str, Any], cfgs: dict[str, Any]) -> None:
        """Once stage `name`'s (the coarse stage's) held-out pilots found the scene's plateau (`gaussians.stopping`),
        before its models train: print the estimate of the stages still to run, the coarse models
        among them, with that plateau in place of the expected one (the models and G_f stop at
        the margin times it, the members carry on from where their pilots ended), and record it
        (`estimate_after_pilots`). Nothing where a budget set the stages' lengths or the coarse
        stage was not estimated."""
        if self.facts is None or self.budget_s or name not in self.pending:
            return
        left = self.pending[self.pending.index(name) :]
        plateau = stop["plateau"]
        facts = dataclasses.replace(self.facts, plateau=plateau, pilot_ends=tuple(stop["pilot_iterations"].values()))
        estimate = per_stage(stage_seconds(self.calibration(), cfgs, facts), left)
        what = f"estimate of the rest, the {name} pilots' plateau at {plateau} (expected {facts.expected_plateau})"
        log(estimate_line(estimate, what))
        ws.write_run_record({**ws.run_record(), "estimate_after_pilots": estimate})


def hull_loo_iou(info: dict[str, Any]) -> float | None:
    """The training photos' leave-one-out silhouette IoU as prepare's mirror check recorded it
    (scene.json), with the best mirror plane's images whether or not they were kept: how well
    the object's hull predicts a photo it was not carved from. None without it (no masks, no check)."""
    return (info.get("mirror") or {}).get("leave_one_out_iou_mirrored")


END_S = 3.0  # what a run takes after its last stage (the summary, the process's end)
BOXED_FIELDS = ("iterations", "refine_stop", "max_seconds")


def _boxed_fields(cfg: TrainConfig) -> dict[str, Any]:
    return {f: getattr(cfg, f) for f in BOXED_FIELDS}


def _pending(ws: Workspace, runs: tuple[str, ...], cfgs: dict[str, Any]) -> tuple[str, ...]:
    """The stages of `runs` (in the registry's order) after the first that `wgs all` will run: those
    not finished with their config, those whose inputs changed since they ran, and every stage that
    reads one of these."""
    pending: list[str] = []
    for t in runs:
        if t == FIRST:
            continue
        inputs_changed = (ws.manifest(t) or {}).get("upstream") != ws.upstream_fingerprints(t)
        if not _fresh(ws, t, cfgs[t]) or inputs_changed or set(UPSTREAM[t]) & set(pending):
            pending.append(t)
    return tuple(pending)


def _fresh(ws: Workspace, table: str, cfg: Any, fields: dict[str, Any] | None = None) -> bool:
    """Whether the stage of config table `table` last ran with `cfg` (with `fields` over it)."""
    held = (ws.manifest(table) or {}).get("config")
    want = as_dict(dataclasses.replace(cfg, **fields) if fields else cfg)
    return held is not None and fingerprint(held) == fingerprint(want)
