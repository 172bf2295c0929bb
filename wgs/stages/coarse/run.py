"""Stage 1: coarse 3DGS `G_c` on the sparse training views, its renders and their Haar subbands;
with `ensemble` > 1 also that many - 1 more coarse models from other seeds or carried on from the
held-out rule's pilots (`members/`), whose repaired renders the repair stage averages with G_c's."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from pathlib import Path

import torch

from ...cost import loop_iterations
from ...curves import test_probe, write_curve
from ...gaussians.callbacks import Probe
from ...gaussians.splats import VIEWER_SH_DEGREE, Splats, export_ply, save_checkpoint, to_world
from ...gaussians.stopping import (
    Curve,
    mean_curve,
    pilot_cap,
    plateau_iteration,
    plateau_past,
    smoothed,
    still_gaining,
    stop_iteration,
)
from ...gaussians.trainer import TrainResult, render_frame, train_gaussians
from ...io import atomic_write_json
from ...io.checkpoint import read_checkpoint, write_checkpoint
from ...io.exr import write_subbands
from ...io.images import write_png
from ...metrics import psnr
from ...progress import log, progress_bar
from ...resume import Checkpointer
from ...scene.dataset import PreparedScene, composite, halved, load_prepared
from ...threads import map_in_processes, side_by_side
from ...workspace import StageRun, Workspace
from ..shared import background_for, initial_splats, member_file, subbands_hwc
from ..stage import StageEnv
from .settings import CoarseConfig, model_config


def write_coarse_outputs(run: StageRun, scene: PreparedScene, splats: Splats, device: torch.device) -> dict:
    bg = background_for(scene)
    per_view = {}
    for f in scene.colour_views:
        ref = composite(f.pixels, f.mask, bg)
        rgb, _ = render_frame(splats, f, device, bg)
        write_png(run.path("renders", f.name), rgb.numpy())
        stem = f.name.rsplit(".", 1)[0]
        write_subbands(run.output("subbands", "ref", f"{stem}.exr"), subbands_hwc(ref))
        write_subbands(run.output("subbands", "render", f"{stem}.exr"), subbands_hwc(rgb))
        per_view[f.name] = psnr(rgb, ref)
    return per_view


def run_coarse(ws: Workspace, cfg: CoarseConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_staged("coarse", cfg, {"seed": env.seed}, force, lambda run: train_coarse(run, ws, cfg, env))


def train_model(
    ws: Workspace,
    cfg: CoarseConfig,
    device: torch.device,
    seed: int,
    desc: str,
    checkpoint: Checkpointer,
    probe: bool,
    pilot: Path | None = None,
) -> tuple[TrainResult, list[str]]:
    """One coarse model from `seed` (with the test probe: G_c), or carried on from a pilot's state
    saved at `pilot` with every photo; its result and the probe's views. Module level so that a
    spawned process can run it."""
    scene = load_prepared(ws.output("prepare", "prepared"))
    torch.manual_seed(seed)
    test, names = test_probe(ws, scene, cfg, background_for(scene), device) if probe else (None, [])
    res = train_gaussians(
        initial_splats(scene, cfg, seed),
        scene.train,
        cfg,
        device,
        extent=1.0,
        desc=desc,
        seed=seed,
        has_masks=scene.has_masks,
        checkpoint=checkpoint,
        probe=test,
        start=read_checkpoint(pilot) if pilot is not None else None,
    )
    return res, names


def train_pilot(
    ws: Workspace,
    cfg: CoarseConfig,
    device: torch.device,
    seed: int,
    held_out: str,
    end_when_past: bool = True,
    keep: Path | None = None,
) -> Curve:
    """One pilot of the stopping rule: the coarse model at half size without the photo `held_out`
    (its visual hull from the other photos' masks), its PSNR at that photo every `cfg.stop_every`
    iterations until it stops gaining, until it shows that its plateau lies past the point where
    every plateau leaves the run all its iterations (`plateau_past`; not with `end_when_past`
    False, to compare whole curves), or until `pilot_cap` (`gaussians.stopping`); its state at the
    end saved at `keep` (an ensemble member carries on from it). Module level so that a spawned
    process can run it."""
    scene = load_prepared(ws.output("prepare", "prepared"))
    fold = dataclasses.replace(scene, train=[f for f in scene.train if f.name != held_out])
    bg = background_for(scene)
    target = halved(next(f for f in scene.train if f.name == held_out))
    ref = composite(target.pixels, target.mask, bg)

    def stopped(curve: list[dict[str, float]]) -> bool:
        points = [(int(p["iteration"]), p["psnr"]) for p in curve]
        past = end_when_past and plateau_past(points, cfg.iterations / cfg.stop_margin, cfg.stop_tolerance_db)
        return past or not still_gaining(points, cfg.stop_tolerance_db, cfg.stop_patience)

    probe = Probe(
        lambda splats: {"psnr": psnr(render_frame(splats, target, device, bg)[0], ref)},
        every_s=math.inf,
        every_iterations=cfg.stop_every,
        stop=stopped,
    )
    torch.manual_seed(seed)
    res = train_gaussians(
        initial_splats(fold, cfg, seed),
        fold.train,
        dataclasses.replace(
            cfg, half_size_until=1.0, end_iteration=pilot_cap(cfg.iterations, cfg.stop_margin, cfg.stop_patience)
        ),
        device,
        extent=1.0,
        desc=f"coarse pilot without {held_out}",
        seed=seed,
        has_masks=scene.has_masks,
        probe=probe,
        keep_state=keep is not None,
    )
    if keep is not None and res.state is not None:
        write_checkpoint(keep, res.state)
    return [(int(p["iteration"]), p["psnr"]) for p in res.curve]


PILOT_MIN_PHOTOS = 3  # a pilot trains on the others: at least 2 of them


def held_out_stop(
    run: StageRun, ws: Workspace, cfg: CoarseConfig, device: torch.device, seed: int, scene: PreparedScene
) -> dict | None:
    """Where the coarse models stop: pilots that each hold out one photo (`train_pilot`, side by
    side) and their mean curve's plateau (`gaussians.stopping`); None where the rule is off, a
    time budget sets the length, or the scene has too few photos. Saved, so that a resumed stage
    stops where it meant to."""
    photos = [f.name for f in scene.colour_views]
    if cfg.stop != "held-out" or cfg.max_seconds or len(photos) < PILOT_MIN_PHOTOS:
        return None
    k = min(len(photos), cfg.stop_pilots)
    photos = [photos[i * len(photos) // k] for i in range(k)]
    saved = run.checkpointer("stop")
    found = saved.load()
    if found is not None:
        log("coarse: the pilots ran before the interruption: their stop is kept")
        return found
    started = time.perf_counter()
    pixels = scene.train[0].width * scene.train[0].height // 4
    workers = side_by_side(len(photos), cfg.iterations, pixels, device.type == "cpu")
    jobs = [(ws, cfg, device, seed, name, True, pilot_state(run, cfg, i)) for i, name in enumerate(photos)]
    curves: dict[str, Curve] = {}
    with progress_bar("coarse pilots", len(jobs)) as bar:
        for i, curve in map_in_processes(train_pilot, jobs, workers):
            curves[photos[i]] = curve
            bar.update(bar.task_ids[0], advance=1, status=f"without {photos[i]}: {curve[-1][0]} iterations")
    mean = smoothed(mean_curve([curves[p] for p in photos]), cfg.refine_every)  # in one order: the same sums
    plateau = plateau_iteration(mean, cfg.stop_tolerance_db)
    record = {
        "rule": "held-out",
        "plateau": plateau,
        "stop_at": stop_iteration(plateau, cfg.stop_margin, cfg.stop_min_iterations, cfg.iterations),
        "held_out_psnr": dict(mean)[plateau],
        "best_psnr": max(s for _, s in mean),
        "pilot_iterations": {p: curves[p][-1][0] for p in photos},
        "mean_curve": mean,
        "pilots_s": round(time.perf_counter() - started, 2),  # their wall time, side by side
    }
    saved.save(record)
    return record


def pilot_state(run: StageRun, cfg: CoarseConfig, index: int) -> Path | None:
    """Where pilot `index` keeps its state at its end, for ensemble member `index + 1` to carry on
    from (`members_from_pilots`; in the stage's resume folder, gone when the stage ends)."""
    keep = cfg.members_from_pilots != "never" and index + 1 < cfg.ensemble
    return run.checkpointer(f"pilot{index}").path if keep else None


def member_start(run: StageRun, cfg: CoarseConfig, stop: dict | None, index: int) -> Path | None:
    """The pilot state ensemble model `index` carries on from: pilot `index - 1`'s, where
    `members_from_pilots` says so ("early": the models stop before their last iteration), the pilot
    kept one and ended before the models' stop; None for G_c and the models that train from the start."""
    if index == 0 or stop is None or (cfg.members_from_pilots == "early" and stop["stop_at"] >= cfg.iterations):
        return None
    ends = list(stop["pilot_iterations"].values())
    path = pilot_state(run, cfg, index - 1) if index - 1 < len(ends) else None
    if path is None or ends[index - 1] >= stop["stop_at"] or not path.is_file():
        return None
    return path


def longest_first(cfg: CoarseConfig, starts: list[int]) -> list[int]:
    """The ensemble's models in the order to start them side by side, the most work first (its
    iterations from `starts[i]`, a half-size one a quarter of a full-size one; ties in their own
    order): G_c and the models that train from the start go before the members carried on from the
    pilots, so that no long model starts last and leaves a process idle."""

    def work(i: int) -> float:
        half, full = loop_iterations(model_config(cfg, i), starts[i])
        return half / 4 + full

    return sorted(range(len(starts)), key=lambda i: -work(i))


def train_coarse(run: StageRun, ws: Workspace, cfg: CoarseConfig, env: StageEnv) -> str:
    device, seed = env.device, env.seed
    scene = load_prepared(ws.output("prepare", "prepared"))
    workers = side_by_side(
        cfg.ensemble, cfg.iterations, scene.train[0].width * scene.train[0].height, device.type == "cpu"
    )
    stop = held_out_stop(run, ws, cfg, device, seed, scene)
    if stop is not None:
        cfg = dataclasses.replace(cfg, end_iteration=stop["stop_at"])
        log(
            f"coarse: stops at iteration {stop['stop_at']} of {cfg.iterations}, {cfg.stop_margin:g} x "
            f"{stop['plateau']}, where the held-out PSNR of {len(stop['pilot_iterations'])} pilots (each photo "
            f"held out in turn, half size) came within {cfg.stop_tolerance_db} dB of its best "
            f"({stop['held_out_psnr']:.2f} of {stop['best_psnr']:.2f} dB)"
        )
        if env.pilots_found is not None:
            env.pilots_found(stop)
    ends = cfg.end_iteration or cfg.iterations
    log(
        f"coarse: {cfg.ensemble} model(s) from seeds {seed}..{seed + cfg.ensemble - 1}, {len(scene.train)} views, "
        f"{ends} iterations on {device}" + (f", {workers} side by side" if workers > 1 else "")
    )
    jobs = [
        (
            ws,
            model_config(cfg, i),
            device,
            seed + i,
            "coarse" if i == 0 else f"coarse member {i + 1}/{cfg.ensemble}",
            run.checkpointer("gc" if i == 0 else f"gc{i}"),
            i == 0,
            member_start(run, cfg, stop, i),
        )
        for i in range(cfg.ensemble)
    ]
    pilots = list(stop["pilot_iterations"]) if stop is not None else []
    carried = {i + 1: pilots[i - 1] for i, job in enumerate(jobs) if job[-1] is not None}  # member number: photo
    if carried:
        log(
            f"coarse: {len(carried)} ensemble member(s) carry on from the pilots, each from where its pilot ended, "
            "given the photo it held out"
        )
    results: dict[int, TrainResult] = {}
    probe_names: list[str] = []
    pilot_ends = list(stop["pilot_iterations"].values()) if stop is not None else []
    order = longest_first(cfg, [pilot_ends[i - 1] if job[-1] is not None else 0 for i, job in enumerate(jobs)])
    with progress_bar("coarse models", cfg.ensemble) if workers > 1 else contextlib.nullcontext() as bar:
        for i, (res, names) in map_in_processes(train_model, jobs, workers, order=order):
            results[i] = res
            if i == 0:
                probe_names = names
            else:
                save_checkpoint(run.output("members", member_file(i)), res.splats, scene.norm, res.iterations)
            if bar is not None:
                bar.update(bar.task_ids[0], advance=1, status=f"seed {seed + i}: {res.seconds:.0f} s")
    res = results[0]
    if res.curve:
        write_curve(run.output("curve"), res, probe_names)
    save_checkpoint(run.output("model"), res.splats, scene.norm, res.iterations)
    n_ply = export_ply(run.output("ply"), to_world(res.splats, scene.norm), VIEWER_SH_DEGREE)
    per_view = write_coarse_outputs(run, scene, res.splats, device)
    atomic_write_json(run.path("train_psnr.json"), per_view)
    mean_psnr = sum(per_view.values()) / len(per_view)
    member_s = [round(results[i].seconds, 2) for i in range(1, cfg.ensemble)]
    # train_seconds: G_c alone (trained beside the members when `side_by_side` > 1)
    run.record.update(
        {
            "num_gaussians": n_ply,
            "iterations": res.iterations,
            "train_seconds": round(res.seconds, 2),
            "final_loss": res.losses[-1],
            "train_psnr": round(mean_psnr, 3),
            "seed": seed,
            "device": str(device),
            "ensemble": cfg.ensemble,
            "member_seconds": member_s,
            "side_by_side": workers,
            "stopping": stop,
            "carried_members": carried,
        }
    )
    return (
        f"coarse: {n_ply} Gaussians, training-view PSNR {mean_psnr:.2f} dB, {res.seconds:.1f} s"
        + (f"; {cfg.ensemble - 1} more ensemble members in {sum(member_s):.1f} s" if member_s else "")
        + (f" ({workers} side by side)" if workers > 1 else "")
    )


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_coarse", "train_pilot"]
