"""Stage 6: PSNR / SSIM / LPIPS of G_f (and G_c, to show the repair's gain) on the test views,
and the error-against-run-time report. The scores are in `scoring`, the shape scores in `shape`,
the reports (md, HTML, plot, summary lines) in `report` and `html`."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from ... import __version__
from ...gaussians.splats import load_checkpoint
from ...gaussians.trainer import render_frame
from ...io import atomic_write_json
from ...io.images import write_gif
from ...lpips import LPIPS, LpipsUnavailable
from ...progress import log
from ...scene.dataset import load_prepared
from ...scene.orbit import orbit_frames
from ...shape.hull import load_grid
from ...workspace import StageRun, Workspace
from ..shared import background_for, coarse_members, stage_times
from ..stage import StageEnv
from .report import curve_points, summary_lines, write_html, write_report
from .scoring import METRICS_DOC, RepairGain, evaluate_model, localised, spread, summarise
from .settings import EvalConfig
from .shape import masks_note, shape_reference


def run_eval(ws: Workspace, cfg: EvalConfig, env: StageEnv, force: bool = False) -> bool:
    """Evaluate `env.final` (fine, or coarse when the repair stages were left out) and G_c."""
    return ws.run_staged(
        "eval",
        cfg,
        {"final": env.final},
        force,
        lambda run: evaluate(run, ws, cfg, env.device, env.final, env.seed),
        requires=("prepare", "coarse", env.final),
    )


def evaluate(run: StageRun, ws: Workspace, cfg: EvalConfig, device: torch.device, final: str, seed: int) -> str:
    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    kind = "test" if scene.test else "training"  # without test views: what the scene itself can show
    if not scene.test:
        log("eval: no test views: the models' fit at the training photos and the leave-one-out silhouettes")
    frames = (scene.test[: cfg.max_views] if cfg.max_views else scene.test) or scene.photos  # not mirror views
    try:
        lpips_fn, lpips_note = LPIPS(cfg.lpips_net, cfg.lpips_weights).to(device), None
    except LpipsUnavailable as exc:
        lpips_fn, lpips_note = None, str(exc)
        log(f"eval: {exc}")
    bg = background_for(scene)
    t0 = time.perf_counter()
    # test cameras posed by wgs with the training photos carry its pose error: localised on the final model
    localise_steps = cfg.localise_steps if kind == "test" and scene.info.get("format") == "photos" else 0
    cameras: dict[str, Any] | None = None
    results: dict[str, Any] = {}
    pers: dict[str, Any] = {}
    gain = repair_gain = None
    want_gain = cfg.repair_gain and final == "fine" and ws.manifest("finetune") is not None and kind == "test"
    for key, st in (("fine", final), ("coarse", "coarse")):
        if key == "coarse" and final == "coarse":
            results["coarse"] = results["fine"]
            continue
        if key == "coarse" and want_gain:  # G_c is the ensemble's first member: loaded and rendered once
            members = coarse_members(ws, scene, device)
            names = {f.name for f in spread(frames, cfg.repair_gain_views)}
            splats, repair_gain = members[0], RepairGain(ws, members, device, bg, seed, names)
        else:
            splats, _ = load_checkpoint(ws.output(st, "model"), scene.norm, device)
        if key == "fine" and localise_steps:  # first: G_c and the baseline are scored at the same cameras
            frames, cameras = localised(splats, frames, bg, localise_steps)
            atomic_write_json(run.path("test_cameras.json"), cameras)
            log(
                f"eval: {len(frames)} test cameras localised on the {final} model ({localise_steps} steps each): "
                f"median move {cameras['median_rotation_deg']:.2f} deg and {100 * cameras['median_shift']:.1f} % "
                "of the camera's distance; the scores are taken there"
            )
        out = run.path("renders", "x").parent if key == "fine" else None
        outlines = run.path("outlines", "x").parent if key == "fine" else None
        per = evaluate_model(
            splats,
            frames,
            device,
            bg,
            lpips_fn,
            out,
            on_view=repair_gain,
            outline_dir=outlines,
            desc=f"eval {st}" + (" and the repair gain" if repair_gain else ""),
        )
        if key == "fine":
            final_splats = splats  # the turntable renders it again, without a second load
        atomic_write_json(run.path("per_view.json" if key == "fine" else "per_view_coarse.json"), per)
        pers[key] = per
        results[key] = {
            **summarise(per),
            "num_gaussians": int(splats["means"].shape[0]),
            "num_views": len(frames),
            "views": kind,
            "test_cameras_localised": cameras
            and {k: v for k, v in cameras.items() if k.startswith(("steps", "median"))},
        }
        if repair_gain is not None:
            gain = repair_gain.summary()
            atomic_write_json(
                run.path("per_view_repair.json"), {"render": repair_gain.before, "repaired": repair_gain.after}
            )
    if ws.status("baseline") == "stale":
        log("eval: the plain-3DGS baseline belongs to earlier stages and is left out (`wgs baseline` trains it again)")
    if ws.status("baseline") == "fresh":
        b = ws.manifest("baseline") or {}
        b_splats, _ = load_checkpoint(ws.output("baseline", "model"), scene.norm, device)
        per = evaluate_model(b_splats, frames, device, bg, lpips_fn, desc="eval baseline")
        results["baseline_3dgs"] = {
            **summarise(per),
            "num_gaussians": int(b_splats["means"].shape[0]),
            **{k: b[k] for k in ("budget_s", "train_seconds", "iterations")},
        }
    carved = ws.output("repair", "carved_hull")
    shape = shape_reference(
        scene, frames if kind == "test" else [], cfg.hull_resolution, load_grid(carved) if carved.is_file() else None
    )
    if shape is not None:
        per_view = ("hull_test", "carved_hull_test", "leave_one_out")
        atomic_write_json(run.path("per_view_shape.json"), {k: shape.pop(f"{k}_per_view") for k in per_view})
        shape["mirror"] = scene.info.get("mirror")
        shape["own_shape"] = (ws.manifest("repair") or {}).get("own_shape")
    res = results_record(
        ws,
        cfg,
        final,
        seed,
        results,
        gain,
        shape,
        masks_note(scene),
        lpips_fn.sources if lpips_fn else None,
        lpips_note,
    )
    atomic_write_json(run.output("results"), res)
    write_report(
        run,
        stage_times(ws),
        results["coarse"],
        results["fine"],
        time.perf_counter() - t0,
        lpips_note,
        res["curves"],
        results.get("baseline_3dgs"),
        shape,
        res["masks_note"],
        (res["estimate_s"] or {}).get("eval"),
    )
    if cfg.turntable_frames > 0:
        write_gif(
            run.path("turntable.gif"),
            [
                render_frame(final_splats, f, device, bg)[0].numpy()
                for f in orbit_frames(scene.train, cfg.turntable_frames)
            ],
        )
    write_html(
        run,
        ws,
        frames,
        bg,
        pers,
        {**results, "shape": shape, "masks_note": res["masks_note"]},
        time.perf_counter() - t0,
        lpips_note,
        gain,
    )
    run.record.update(
        {"psnr": res["psnr"], "ssim": res["ssim"], "lpips": res["lpips"], "coarse_psnr": results["coarse"]["psnr"]}
    )
    return "\n".join(summary_lines(results, shape, gain))


def results_record(
    ws: Workspace,
    cfg: EvalConfig,
    final: str,
    seed: int,
    results: dict[str, Any],
    gain: dict | None,
    shape: dict | None,
    note: str | None,
    lpips_sources: dict | None,
    lpips_note: str | None,
) -> dict[str, Any]:
    """results.json: G_f's scores at the top level, G_c's, the baseline's, the shape scores, the
    stage times beside their estimate, and the nerfstudio `ns-eval` keys."""
    res = {
        **results["fine"],
        "final_model": final,
        "coarse": results["coarse"],
        "baseline_3dgs": results.get("baseline_3dgs"),
        "repair_gain": gain,
        "shape": shape,
        "masks_note": note,
        "lpips_net": cfg.lpips_net if lpips_sources else None,
        "lpips_unavailable": lpips_note,
        "metrics": METRICS_DOC,
        "lpips_weights": lpips_sources,
        "stage_times_s": {r["stage"]: r["wall_time_s"] for r in stage_times(ws)},
        "estimate_s": ws.run_record().get("estimate"),
        "budget_s": ws.run_record().get("budget_s"),
    }
    source = ((ws.manifest("prepare") or {}).get("summary") or {}).get("source")
    res.update(
        {
            "scene": source,
            "method": "wgs" if final == "fine" else "wgs-coarse-only",
            "version": __version__,
            "seed": seed,
            # the nerfstudio `ns-eval` layout, for tools that read it
            "experiment_name": Path(str(source)).name if source else ws.root.name,
            "method_name": "wgs",
            "checkpoint": str(ws.output(final, "model")),
            "results": {
                k: results["fine"][k]
                for k in ("psnr", "psnr_std", "ssim", "ssim_std", "lpips", "lpips_std")
                if k in results["fine"]
            },
        }
    )
    # what error_vs_time.png shows: (cumulative s, probe-view PSNR) per training loop
    res["curves"] = curve_points(ws, stage_times(ws), "baseline_3dgs" in results)
    return res


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_eval"]
