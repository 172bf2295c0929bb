"""How long `wgs all` takes on this machine, the working size chosen for it, and the plan that fits
a time budget.

A calibration of about 3 s times, on this machine and device, a training view's core at two sizes
(the rasterizer's forward + backward on a synthetic cloud, and the photometric loss's), a training
step of the repair network D and its forward pass.
A stage's time is then its work in those units (iterations, views, pixels, D steps and forwards)
times a factor measured on whole runs (`FACTOR`, docs/speed.md "Working size, estimate and
budget"), plus a fixed part in D-step units. The estimate is printed before training and kept in
`WS/run.json`; the report puts it beside the stages' actual times.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .config import (
    CPU_TARGET_S,
    GPU_MAX_SIZE,
    STAGE_OF_TABLE,
    TABLE_OF,
    UNASKED,
    CoarseConfig,
    FineConfig,
    MaskDataConfig,
    TrainConfig,
    as_dict,
    time_boxed,
)
from .errors import InputError
from .gaussians.stopping import StopParams, pilot_cap
from .io import atomic_write_json
from .progress import log
from .scene.prepare import downscale_for
from .threads import side_by_side
from .workspace import Workspace, fingerprint

CALIBRATION_SIDES = (128, 256)  # square views the rasterizer is timed at
CALIBRATION_GAUSSIANS = 8000  # about a 4-view model's size at 200 px
MIN_SIZE = 96  # no working size below this long side (px), whatever the budget
# the training stages' share of a budget is time-boxed with iteration caps this many times the
# planned rate, so that the time, not the caps, ends them even where the calibration was slow
# (1.5 let a calibration twice too slow end ethiopianHead's 20-minute budget at 0.80 of it)
HEADROOM = 3.0
# a calibration is reused by the runs of the next hour on the same machine, device, thread count
# and versions (a test suite's many small runs, a batch of scenes), from $WGS_CACHE (default ~/.cache/wgs)
CALIBRATION_MAX_AGE_S = 3600.0
# stage time / modelled work, measured on whole runs (`wgs all` on lego at 200 px and ethiopianHead
# at 307 px, 2026-11-27; docs/speed.md "Working size, estimate and budget")
# one step of eval's test-camera localisation (render, backward, the Gaussians moved) in rendered
# views: 2.4 measured at 200x200 with 20k Gaussians (a random blob, tests/test_localise.py's)
LOCALISE_STEP_VIEWS = 2.5
FACTOR = {"coarse": 1.0, "mask_data": 0.8, "finetune": 1.75, "repair": 0.9, "fine": 0.93, "eval": 0.9}
# a training loop's time grows with the share of the frame the object covers (more Gaussians, more
# of them on each pixel), which the calibration's fixed synthetic cloud does not see: the training
# stages' factors are times 1 + MASK_SHARE_SLOPE x (mask share - FIT_MASK_SHARE), at least
# MIN_SHARE_FACTOR. FIT_MASK_SHARE: lego's 4 views, on which FACTOR was fitted; the slope from one
# generated close-up (0.786 of its photos), checked on kinds of capture left out of that fit
# (docs/speed.md "The estimate on captures it was not fitted on")
FIT_MASK_SHARE = 0.245
MASK_SHARE_SLOPE = 1.4
MIN_SHARE_FACTOR = 0.5
# the training stages of a scene without masks: the background is reconstructed too, with about
# 4x the Gaussians (the fox at 213x379, 2026-11-27)
NO_MASKS_FACTOR = 1.9
# a stage's fixed part (loading, renders, files, the shape and carve steps), in D training steps
FIXED_STEPS = {
    "prepare": 20,
    "coarse": 25,
    "mask_data": 15,
    "finetune": 20,
    "repair": 35,
    "fine": 10,
    "eval": 10,
    "baseline": 10,
}
# the baseline trains plain 3DGS for as long as these stages took (`stages.baseline`)
BASELINE_BUDGET = ("coarse", "mask_data", "finetune", "repair", "fine")
D_STEP_BATCH, D_STEP_CROP, D_STEP_CHANNELS = 16, 32, 32  # the D training step timed
# the HF U-Net U: a step's cost in D steps, and the share of its step limit it runs on average (it
# stops early where it does not beat no repair: 250 of 1500 steps on lego, all 1500 on ethiopianHead)
U_STEP_SHARE, U_STEPS_RUN = 0.3, 0.5
# side-by-side coarse models (one thread each, `threads.side_by_side`) train this many
# times as fast, together, as one model on every thread (measured on 2 cores, wgs/threads.py)
SIDE_BY_SIDE_THROUGHPUT = 1.5
PREPARE_S_PER_MEGAPIXEL = 0.08  # reading, undistorting and downscaling a photo, per full-size megapixel
TRAIN_STAGES = ("coarse", "mask_data", "fine")
UNASKED_TABLES = tuple(TABLE_OF[name] for name in UNASKED)  # what `wgs all` runs unless asked for more


@dataclass(frozen=True)
class Calibration:
    """Timings on this machine: a training view's rasterizer and photometric loss, forward and
    backward, as `intercept + slope * pixels` seconds; D's training step (batch 16 of 32x32 crops, 32 channels) and D's
    forward pass per pixel of its input."""

    raster: tuple[float, float]
    d_step_s: float
    d_forward_s_per_pixel: float
    threads: int
    device: str
    seconds: float

    def view_s(self, pixels: float) -> float:
        intercept, slope = self.raster
        return intercept + slope * pixels


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


def cached_calibration(device: torch.device, now: float | None = None) -> Calibration:
    """`calibrate(device)`, or the calibration of this machine made within CALIBRATION_MAX_AGE_S."""
    path, key, now = cache_dir() / "calibration.json", machine_key(device), time.time() if now is None else now
    try:
        held = json.loads(path.read_text(encoding="utf-8"))
        entry = held.get(key) if isinstance(held, dict) else None
        if entry and 0 <= now - entry["made"] <= CALIBRATION_MAX_AGE_S:
            return Calibration(**{**entry["calibration"], "raster": tuple(entry["calibration"]["raster"])})
    except (OSError, ValueError, KeyError, TypeError):
        held = {}
    cal = calibrate(device)
    try:
        fresh = {
            k: v
            for k, v in (held if isinstance(held, dict) else {}).items()
            if isinstance(v, dict) and now - v.get("made", 0) <= CALIBRATION_MAX_AGE_S
        }
        atomic_write_json(path, {**fresh, key: {"made": now, "calibration": dataclasses.asdict(cal)}})
    except OSError:
        pass  # a read-only home: calibrate every run
    return cal


@dataclass(frozen=True)
class SceneFacts:
    """What a scene's cost depends on: its working size (px), its training and test views, its
    photos' size before downscaling (prepare reads them), and whether it has masks."""

    width: int
    height: int
    n_train: int
    n_test: int
    full_pixels: int = 0
    has_masks: bool = True
    posed_by_wgs: bool = False  # photos posed by prepare: eval localises the test cameras
    mask_share: float = FIT_MASK_SHARE  # the share of a training photo inside its mask (prepare's record)

    @property
    def pixels(self) -> int:
        return self.width * self.height


# Where the held-out stopping rule's pilots stop gaining, for the estimate made before they run
# (lego, 4 views at 200x200: 400, python -m wgs all ... --downscale 2, 2026-11-28)
EXPECTED_PLATEAU = 400


def expected_iterations(cfg: TrainConfig) -> int:
    """The iterations a loop is expected to run: all of them, or under the held-out stopping rule
    (`gaussians.stopping`) its margin times the expected plateau."""
    if not isinstance(cfg, StopParams) or cfg.stop != "held-out" or cfg.max_seconds:
        return cfg.iterations
    return min(cfg.iterations, max(round(cfg.stop_margin * EXPECTED_PLATEAU), cfg.stop_min_iterations))


def pilots_s(cal: Calibration, cfg: CoarseConfig, facts: SceneFacts, workers: int) -> float:
    """The held-out rule's pilots: one per photo (at most `stop_pilots`) at half size, each until
    `stop_patience` past the expected plateau, at most `pilot_cap`; 0 where the rule is off."""
    if not isinstance(cfg, StopParams) or cfg.stop != "held-out" or cfg.max_seconds:
        return 0.0
    length = min(pilot_cap(cfg.iterations, cfg.stop_margin, cfg.stop_patience), EXPECTED_PLATEAU + cfg.stop_patience)
    share = workers / SIDE_BY_SIDE_THROUGHPUT if workers > 1 else 1
    return math.ceil(min(facts.n_train, cfg.stop_pilots) / workers) * length * cal.view_s(facts.pixels / 4) * share


def cover_factor(facts: SceneFacts) -> float:
    """The training stages' factor for how much of the frame the object covers."""
    if not facts.has_masks:
        return NO_MASKS_FACTOR
    return max(MIN_SHARE_FACTOR, 1.0 + MASK_SHARE_SLOPE * (facts.mask_share - FIT_MASK_SHARE))


def _loop_s(cal: Calibration, cfg: TrainConfig, pixels: float, renders: float = 1.0) -> float:
    """One training loop's modelled seconds: its expected iterations, those in the first
    `half_size_until` of the schedule at half size."""
    ends = expected_iterations(cfg)
    half = min(ends, cfg.half_size_until * cfg.iterations)
    return (half * cal.view_s(pixels / 4) + (ends - half) * cal.view_s(pixels)) * renders


def loops(cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts) -> dict[str, tuple[int, float, float]]:
    """Each training stage's (loops run one after another, modelled seconds of one loop, stage factor)."""
    coarse: CoarseConfig = cfgs["coarse"]
    workers = side_by_side(coarse.ensemble, coarse.iterations, facts.pixels, torch.device(cal.device).type == "cpu")
    fine: FineConfig = cfgs["fine"]
    mask: MaskDataConfig = cfgs["mask_data"]
    masks = cover_factor(facts)
    return {
        "coarse": (
            math.ceil(coarse.ensemble / workers),
            _loop_s(cal, coarse, facts.pixels) * (workers / SIDE_BY_SIDE_THROUGHPUT if workers > 1 else 1),
            FACTOR["coarse"] * masks,
        ),
        "mask_data": (
            facts.n_train if mask.strategy == "loo" else 1,
            _loop_s(cal, mask, facts.pixels),
            FACTOR["mask_data"] * masks,
        ),
        "fine": (
            max(1, fine.rounds),
            _loop_s(cal, fine, facts.pixels, renders=1 + 1 / max(fine.pseudo_every, 1)),
            FACTOR["fine"] * masks,
        ),
    }


def stage_seconds(cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts) -> dict[str, float]:
    """Modelled wall time of each stage (config table -> seconds) for the stage configs `cfgs`
    (config table -> config) on a scene with `facts`."""
    fixed = {k: v * cal.d_step_s for k, v in FIXED_STEPS.items()}
    out = {
        "prepare": fixed["prepare"] + PREPARE_S_PER_MEGAPIXEL * (facts.n_train + facts.n_test) * facts.full_pixels / 1e6
    }
    for table, (count, loop, factor) in loops(cal, cfgs, facts).items():
        cfg = cfgs[table]
        if cfg.max_seconds:
            loop, factor = min(loop * factor, cfg.max_seconds), 1.0
        out[table] = fixed[table] + count * loop * factor
    coarse = cfgs["coarse"]
    pilots = side_by_side(
        min(facts.n_train, coarse.stop_pilots),
        coarse.iterations,
        facts.pixels // 4,
        torch.device(cal.device).type == "cpu",
    )
    out["coarse"] += FACTOR["coarse"] * cover_factor(facts) * pilots_s(cal, coarse, facts, pilots)
    ft, ev = cfgs["finetune"], cfgs["eval"]
    d_pixels = facts.pixels / 4**ft.levels if ft.domain == "wavelet" else facts.pixels
    d_steps = ft.prior_steps if ft.prior != "none" else ft.d_steps
    width = (ft.d_channels / D_STEP_CHANNELS) ** 2 * (ft.d_batch * ft.d_crop**2) / (D_STEP_BATCH * D_STEP_CROP**2)
    u_steps = ft.u_max_steps * U_STEPS_RUN if ft.use_u and ft.domain == "wavelet" else 0
    # D's held-out check: SDEdit on the held-out pairs (about 44 pairs from G_d) every prior_eval_every steps
    checks = (
        (d_steps // max(ft.prior_eval_every, 1) + 1)
        * math.ceil(44 * ft.holdout)
        * math.ceil(ft.eval_steps * ft.eval_strength)
    )
    steps_s = cal.d_step_s * (FACTOR["finetune"] * d_steps * width + u_steps * U_STEP_SHARE)
    out["finetune"] = fixed["finetune"] + steps_s + checks * d_pixels * cal.d_forward_s_per_pixel
    rp = cfgs["repair"]
    ensemble = cfgs["coarse"].ensemble
    pseudo = rp.num_views if rp.poses == "sphere" else rp.views_per_train * facts.n_train
    forwards = math.ceil(rp.steps * rp.strength) * rp.symmetries
    per_render = forwards * d_pixels * cal.d_forward_s_per_pixel + cal.view_s(facts.pixels) / 2
    out["repair"] = fixed["repair"] + FACTOR["repair"] * ensemble * pseudo * per_render * max(1, cfgs["fine"].rounds)
    n_eval = min(facts.n_test, ev.max_views or facts.n_test)
    gain = min(ev.repair_gain_views or n_eval, n_eval) if ev.repair_gain else 0
    out["eval"] = fixed["eval"] + FACTOR["eval"] * (
        n_eval * cal.view_s(facts.pixels)
        + gain * ensemble * per_render
        + ev.turntable_frames * cal.view_s(facts.pixels) / 2
        + (n_eval * ev.localise_steps * LOCALISE_STEP_VIEWS * cal.view_s(facts.pixels) if facts.posed_by_wgs else 0)
    )
    out["baseline"] = fixed["baseline"] + sum(out[t] for t in BASELINE_BUDGET)
    return {k: round(v, 1) for k, v in out.items()}


def per_stage(model: dict[str, float], tables: tuple[str, ...]) -> dict[str, float | None]:
    """The modelled seconds of each of `tables`, None (unknown) for a table the cost model lacks."""
    return {t: model.get(t) for t in tables}


def choose_downscale(
    cal: Calibration,
    cfgs: dict[str, Any],
    facts: SceneFacts,
    target_s: float | None,
    runs: tuple[str, ...] = UNASKED_TABLES,
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
    cal: Calibration, cfgs: dict[str, Any], facts: SceneFacts, left_s: float, runs: tuple[str, ...] = tuple(FACTOR)
) -> dict[str, Any]:
    """The training stages in `runs` time-boxed so that the stages in `runs` take `left_s` seconds:
    what the others are modelled to take is set aside, the rest shared among coarse, mask-data and
    fine in proportion to their modelled times. Returns {"stages": table -> time-boxed config,
    "seconds": table -> planned seconds}."""
    model = stage_seconds(cal, cfgs, facts)
    fixed_s = {k: v * cal.d_step_s for k, v in FIXED_STEPS.items()}
    if "baseline" in runs:  # it trains as long again as the method's stages take: they get half of the rest
        after = sum(model[t] for t in runs if t not in BASELINE_BUDGET and t != "baseline")
        left_s = (left_s - after - fixed_s["baseline"]) / 2 + after
    others = [t for t in ("finetune", "repair", "eval") if t in runs]
    trained = [t for t in TRAIN_STAGES if t in runs]
    train = max(left_s - sum(model[t] for t in others) - sum(fixed_s[t] for t in trained), 1.0)
    modelled = {t: v for t, v in loops(cal, cfgs, facts).items() if t in runs}
    total = sum(count * loop * factor for count, loop, factor in modelled.values())
    stages, seconds = {}, {}
    for table, (count, loop, factor) in modelled.items():
        share = train * count * loop * factor / total
        per_loop = share / count
        stages[table] = time_boxed(cfgs[table], per_loop, loop * factor, HEADROOM)
        seconds[table] = round(fixed_s[table] + share, 1)
    for table in others:
        seconds[table] = model[table]
    if "baseline" in runs:
        seconds["baseline"] = round(fixed_s["baseline"] + sum(seconds[t] for t in BASELINE_BUDGET if t in seconds), 1)
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
        self.runs = UNASKED_TABLES + tuple(TABLE_OF[name] for name in asked)
        self.started = time.perf_counter()
        self._cal: Calibration | None = None
        self.key = f"budget {budget_s:g} s" if budget_s else f"machine ({device.type})"

    def calibration(self) -> Calibration:
        if self._cal is None:
            self._cal = cached_calibration(self.device)
        return self._cal

    def __call__(self, width: int, height: int, n_train: int, n_test: int) -> tuple[int, str]:
        """The working size (`stages.WorkingSize`)."""
        if self.device.type != "cpu" and not self.budget_s:
            k = downscale_for(width, height, GPU_MAX_SIZE)
            return k, (
                f"working size: {width // k}x{height // k} (the photos' {width}x{height} / {k}): a long side "
                f"of at most {GPU_MAX_SIZE} px on a GPU; --max-size or --downscale set it"
            )
        cal = self.calibration()
        target = self.budget_s or CPU_TARGET_S
        facts = SceneFacts(
            width, height, n_train, n_test, full_pixels=width * height, has_masks=self.cfgs["prepare"].masks != "none"
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
        return k, (
            f"working size: {width // k}x{height // k} ({why}; {cal.device}, {cal.threads} threads); "
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
        pending = tuple(t for t in runs if t != "prepare" and not _fresh(ws, t, cfgs[t]))
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
                },
            )
        elif held.get("estimate"):
            record.update({k: held[k] for k in ("estimate", "calibration", "scene") if k in held})
        ws.write_run_record(record)
        return cfgs


END_S = 3.0  # what a run takes after its last stage (the summary, the process's end)
BOXED_FIELDS = ("iterations", "refine_stop", "max_seconds")


def _boxed_fields(cfg: TrainConfig) -> dict[str, Any]:
    return {f: getattr(cfg, f) for f in BOXED_FIELDS}


def _fresh(ws: Workspace, table: str, cfg: Any, fields: dict[str, Any] | None = None) -> bool:
    """Whether the stage of config table `table` last ran with `cfg` (with `fields` over it)."""
    held = (ws.manifest(STAGE_OF_TABLE[table]) or {}).get("config")
    want = as_dict(dataclasses.replace(cfg, **fields) if fields else cfg)
    return held is not None and fingerprint(held) == fingerprint(want)
