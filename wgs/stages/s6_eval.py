"""Stage 6: PSNR / SSIM / LPIPS of G_f (and G_c, to show the repair's gain) on the test views,
and the error-against-run-time report."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from .. import __version__
from ..config import EvalConfig
from ..curves import read_curve
from ..errors import InputError
from ..gaussians.splats import load_checkpoint
from ..gaussians.trainer import render_frame
from ..io import atomic_write_bytes, atomic_write_json, read_json
from ..io.images import write_gif, write_png
from ..lpips import LPIPS, LpipsUnavailable
from ..metrics import psnr, ssim
from ..progress import fmt, log, progress_bar
from ..report_html import outline_sheet
from ..scene.dataset import Frame, composite, load_prepared
from ..scene.orbit import orbit_frames
from ..shape.hull import HullGrid, load_grid, silhouette, visual_hull_grid
from ..shape.own_shape import describe as describe_own_shape
from ..shape.scores import SILHOUETTE_DOC, leave_one_out, mean_scores, silhouette_scores
from ..workspace import StageRun, Workspace
from . import StageEnv
from .shared import (
    background_for,
    coarse_members,
    ensemble_repair,
    stage_times,
    workspace_repairer,
)

METRICS_DOC = {
    "psnr": "mean over views of per-view PSNR (dB), images in [0, 1] on the dataset background",
    "ssim": "11x11 Gaussian window, sigma 1.5, zero padding, mean of the map (3DGS / GaussianObject code)",
    "lpips": "LPIPS v0.1 in plain torch from local torchvision-format weights",
    "silhouette": SILHOUETTE_DOC,
}
SILHOUETTE_KEYS = ("iou", "excess", "missed")


def evaluate_model(splats, frames, device, bg, lpips_fn, out_dir=None, desc="eval",
                   on_view: Callable[[Frame, torch.Tensor, torch.Tensor], None] | None = None,
                   outline_dir: Path | None = None) -> dict[str, dict[str, float]]:
    """Per-view PSNR / SSIM (/ LPIPS) of `splats` at `frames`, and where a frame has a mask its
    silhouette scores (silhouette_iou, silhouette_excess, silhouette_missed); renders go to
    `out_dir`, outline sheets (`report_html.outline_sheet`) to `outline_dir`.
    `on_view(frame, render, truth)` sees each render too (the repair gain reuses G_c's instead of
    rendering it again)."""
    per: dict[str, dict[str, float]] = {"psnr": {}, "ssim": {}, "lpips": {}}
    per.update({f"silhouette_{k}": {} for k in SILHOUETTE_KEYS})
    with progress_bar(desc, len(frames)) as prog:
        for i, f in enumerate(frames):
            rgb, alpha = render_frame(splats, f, device, bg)
            ref = composite(f.image, f.mask, bg)
            per["psnr"][f.name] = psnr(rgb, ref)
            per["ssim"][f.name] = ssim(rgb, ref)
            if f.mask is not None:
                pred, true = alpha[..., 0] > 0.5, f.mask > 0.5
                for k, v in silhouette_scores(pred, true).items():
                    per[f"silhouette_{k}"][f.name] = v
                if outline_dir is not None:
                    write_png(outline_dir / f.name, outline_sheet(rgb.numpy(), true.numpy(), pred.numpy()))
            if lpips_fn is not None:
                with torch.no_grad():
                    per["lpips"][f.name] = float(lpips_fn(rgb.permute(2, 0, 1)[None].to(device),
                                                          ref.permute(2, 0, 1)[None].to(device)))
            if out_dir is not None:
                write_png(out_dir / f.name, rgb.numpy())
            if on_view is not None:
                on_view(f, rgb, ref)
            prog.update(0, completed=i + 1)
    return {k: v for k, v in per.items() if v}


def spread(frames: list[Frame], k: int) -> list[Frame]:
    """k of the frames at evenly spaced positions in their order (all of them when k is 0 or >= their number)."""
    n = len(frames)
    return frames if k <= 0 or k >= n else [frames[i * n // k] for i in range(k)]


class RepairGain:
    """PSNR of G_c's render and of the pseudo reference `wgs repair` makes at the same camera (the
    ensemble's renders repaired by D + U, averaged) against the truth at the test poses: how much
    the repair itself fixes, before any 3D training on it. Called per view with G_c's render;
    scores the views named in `names` and passes over the others."""

    def __init__(self, ws: Workspace, members, device, bg, seed: int, names: set[str]):
        self.members, self.device, self.bg, self.names = members, device, bg, names
        self.repairer = workspace_repairer(ws, device, seed)
        self.before: dict[str, float] = {}
        self.after: dict[str, float] = {}

    def __call__(self, frame: Frame, render: torch.Tensor, truth: torch.Tensor) -> None:
        if frame.name not in self.names:
            return
        _, fixed, _, _ = ensemble_repair(self.members, frame, self.bg, self.repairer, self.device, first_render=render)
        self.before[frame.name], self.after[frame.name] = psnr(render, truth), psnr(fixed, truth)

    def summary(self) -> dict[str, Any]:
        gains = [self.after[k] - self.before[k] for k in self.before]
        return {"psnr_render": statistics.fmean(self.before.values()),
                "psnr_repaired": statistics.fmean(self.after.values()),
                "gain_db": statistics.fmean(gains), "gain_std": statistics.pstdev(gains),
                "views_improved": sum(g > 0 for g in gains), "num_views": len(gains),
                "prior": self.repairer.meta.prior, "ensemble": len(self.members)}


def summarise(per: dict[str, dict[str, float]]) -> dict[str, float | None]:
    """Mean and spread over views of each metric (None where it was not measured)."""
    out: dict[str, float | None] = {}
    for m in ("psnr", "ssim", "lpips", *(f"silhouette_{k}" for k in SILHOUETTE_KEYS)):
        vals = list(per.get(m, {}).values())
        out[m] = statistics.fmean(vals) if vals else None
        out[f"{m}_std"] = statistics.pstdev(vals) if vals else None
    return out


def shape_reference(scene, frames: list[Frame], resolution: int, carved: HullGrid | None = None
                    ) -> dict[str, Any] | None:
    """How fat the visual hull is: the hull of all training masks (every mask agreeing) scored at
    the test views that have masks, the same for the repair stage's carved hull where there is one,
    and the leave-one-out estimate that needs no test views (the hull of the other photos' masks at
    each photo's camera; mirror views play no part in it). None without masks, or where the training
    masks share no region."""
    if not scene.has_masks:
        return None
    try:
        grid = visual_hull_grid(scene.train, resolution, tolerate=0)
        loo = leave_one_out(scene.photos, resolution) if len(scene.photos) >= 2 else {}
    except InputError:
        log("eval: the training masks share no region (every mask agreeing) -> no visual-hull scores")
        return None
    with_mask = [f for f in frames if f.mask is not None]
    test = {f.name: silhouette_scores(silhouette(grid, f)[0], f.mask > 0.5) for f in with_mask}
    carved_test = ({f.name: silhouette_scores(silhouette(carved, f)[0], f.mask > 0.5) for f in with_mask}
                   if carved is not None else {})
    return {"hull_test": mean_scores(test), "carved_hull_test": mean_scores(carved_test),
            "leave_one_out": mean_scores(loo), "hull_resolution": resolution,
            "hull_test_per_view": test, "carved_hull_test_per_view": carved_test, "leave_one_out_per_view": loo}


def masks_note(scene) -> str | None:
    """Where the masks came from when wgs made them (the truth is composited with them), or why the
    automatic ones were not used; and which training photos crop the object."""
    masks = scene.info.get("masks") or {}
    notes = []
    if masks.get("source") == "auto":
        notes.append("The masks are automatic (`wgs prepare --masks auto`): the test views' ground truth is "
                     "composited with them, so these scores measure against wgs's own idea of the object's outline.")
    elif masks.get("auto_failed"):
        notes.append(f"No masks: the automatic ones were not used ({masks['auto_failed']}), so there is no visual "
                     "hull and no silhouette score; `wgs prepare --masks DIR` takes yours.")
    if masks.get("training_cropped"):
        notes.append(f"Training photos that crop the object (their mask reaches the frame's edge): "
                     f"{', '.join(masks['training_cropped'])}; photos that hold the whole object bound more of it.")
    return " ".join(notes) or None


def shape_line(coarse: dict, fine: dict, shape: dict) -> str:
    """One line of silhouette IoUs: hull, G_c and G_f at the test views, and the leave-one-out estimate."""
    parts = []
    if shape["hull_test"] is not None:
        parts.append(f"visual hull {shape['hull_test']['iou']:.3f}")
    if shape.get("carved_hull_test") is not None:
        parts.append(f"carved hull {shape['carved_hull_test']['iou']:.3f}")
    if coarse.get("silhouette_iou") is not None:
        parts.append(f"coarse {coarse['silhouette_iou']:.3f} -> fine {fine['silhouette_iou']:.3f}")
    head = "silhouette IoU at the test views: " + ", ".join(parts) if parts else "no test masks"
    loo, mirror = shape["leave_one_out"], shape.get("mirror")
    if loo is not None:
        head += f"; leave-one-out estimate (hull of the other photos' masks at each photo's camera) {loo['iou']:.3f}"
    if mirror:
        taught = {"outline": " (their outlines)", "full": " (outlines and colours)"}.get(mirror.get("views"), "")
        head += (f"; the photos' mirror images {'are' if mirror['used'] else 'are not'} training views"
                 f"{taught if mirror['used'] else ''} "
                 f"(leave-one-out IoU {mirror['leave_one_out_iou']:.3f} -> {mirror['leave_one_out_iou_mirrored']:.3f}"
                 " with the mirror)")
    if shape.get("own_shape"):
        head += f"; the hull shaped by the photos' masks: {describe_own_shape(shape['own_shape'])}"
    return head


def write_report(run: StageRun, times: list[dict[str, Any]], coarse: dict, fine: dict, eval_s: float,
                 lpips_note: str | None, curves: dict[str, list[tuple[float, float]]] | None = None,
                 baseline: dict | None = None, shape: dict | None = None, masks_note: str | None = None,
                 eval_estimate_s: float | None = None) -> None:
    total = (times[-1]["cumulative_s"] if times else 0.0) + eval_s
    lines = ["# wgs report: error against run time", "",
             "| stage | wall time (s) | estimate (s) | cumulative (s) | peak memory (MiB) | PSNR | SSIM | LPIPS "
             "| silhouette IoU |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in times:
        q = coarse if r["stage"] == "coarse" else fine if r["stage"] == "fine" else None
        qs = ([fmt(q["psnr"], 2), fmt(q["ssim"]), fmt(q["lpips"]), fmt(q.get("silhouette_iou"))] if q
              else ["", "", "", ""])
        lines.append(f"| {r['stage']} | {r['wall_time_s']:.1f} | {fmt(r['estimate_s'], 1, '')} | "
                     f"{r['cumulative_s']:.1f} | {fmt(r['peak_memory_mb'], 0)} | " + " | ".join(qs) + " |")
    lines.append(f"| eval | {eval_s:.1f} | {fmt(eval_estimate_s, 1, '')} | {total:.1f} | | | | | |")
    lines += ["", f"Quality is measured on {fine.get('num_views')} test views (mean over views; "
                  "coarse = G_c, fine = G_f). The estimate is the one printed before training (`wgs.estimate`); "
                  "empty where the stage did not run in that `wgs all`.", ""]
    if shape is not None:
        lines += [shape_line(coarse, fine, shape) + ".",
                  SILHOUETTE_DOC[0].upper() + SILHOUETTE_DOC[1:] + ".", ""]
    if masks_note:
        lines += [masks_note, ""]
    if lpips_note:
        lines += [f"LPIPS not computed: {lpips_note}", ""]
    atomic_write_bytes(run.output("report"), "\n".join(lines).encode())
    plot_error_vs_time(run.path("error_vs_time.png"), times, coarse, fine, curves, baseline)


def curve_points(ws: Workspace, times: list[dict[str, Any]], baseline: bool = False
                 ) -> dict[str, list[tuple[float, float]]]:
    """Each training stage's probe curve as (cumulative wall time s, test PSNR) from its curve
    output; a stage's points start where the stage started, the plain-3DGS baseline's (`baseline`:
    include it) where coarse did."""
    start = {r["stage"]: r["cumulative_s"] - r["wall_time_s"] for r in times}
    out = {}
    curves = [("coarse", "coarse", "coarse"), ("fine", "fine", "fine")]
    if baseline:
        curves.append(("baseline", "plain 3DGS", "coarse"))
    for stage, label, at in curves:
        c = read_curve(ws.output(stage, "curve")) if ws.manifest(stage) is not None else None
        if c and at in start:
            out[label] = [(start[at] + p["seconds"], p["psnr"]) for p in c["points"]]
    return out


def plot_error_vs_time(path, times, coarse, fine, curves: dict[str, list[tuple[float, float]]] | None = None,
                       baseline: dict | None = None) -> None:
    """Test PSNR against cumulative wall time: the training curves (on a few probe views) with stage
    boundaries, and the final evaluation of G_c and G_f (all test views) as points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cum = {r["stage"]: r["cumulative_s"] for r in times}
    pts = [(cum[s], q["psnr"], s) for s, q in (("coarse", coarse), ("fine", fine)) if s in cum and q["psnr"]]
    if baseline is not None and baseline.get("psnr") and "fine" in cum:
        pts.append((cum["fine"], baseline["psnr"], "plain 3DGS"))
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for stage, xy in (curves or {}).items():
        ax.plot([p[0] for p in xy], [p[1] for p in xy], ".-", lw=1, label=f"{stage} training (probe views)")
    for r in times:
        ax.axvline(r["cumulative_s"], color="grey", lw=0.5, ls=":")
    if pts:
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o", color="k", label="eval (all test views)")
        for x, y, s in pts:
            ax.annotate(s, (x, y), textcoords="offset points", xytext=(4, 4))
    ax.set(xlabel="cumulative wall time (s)", ylabel="test PSNR (dB)", title="error against run time")
    if curves or pts:
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_html(run: StageRun, ws: Workspace, frames, bg, pers: dict, results: dict, eval_s: float,
               lpips_note: str | None, gain: dict | None) -> None:
    """report.html beside report.md: the same table plus the views and sheets (wgs/report_html.py)."""
    from ..io.images import read_image
    from ..report_html import error_sheet, worst_and_best, write_report_html

    per_fine = pers.get("fine") or pers.get("coarse") or {"psnr": {}, "ssim": {}}
    by_name = {f.name: f for f in frames}
    sheets = []
    for label, name in worst_and_best(per_fine["psnr"]):
        rendered = run.path("renders", name)
        if not rendered.is_file():
            continue
        f = by_name[name]
        sheet = error_sheet(read_image(rendered)[..., :3], composite(f.image, f.mask, bg).numpy())
        out = run.path("sheets", f"{label}_{name}")
        write_png(out, sheet)
        sheets.append((label, name, out))
    outlines = []
    iou = per_fine.get("silhouette_iou", {})
    for name in sorted(iou, key=iou.get)[:3]:
        if (p := run.path("outlines", name)).is_file():
            outlines.append((f"IoU {iou[name]:.3f}", name, p))
    notes = [f"Quality on {results['fine'].get('num_views')} test views (mean over views); coarse = G_c, "
             f"fine = G_f. Evaluation took {eval_s:.0f} s."]
    if results.get("shape") is not None:
        notes.append(shape_line(results["coarse"], results["fine"], results["shape"]) + ".")
    if gain is not None:
        notes.append(f"Repair gain at the test poses: {gain['gain_db']:+.2f} dB (G_c render "
                     f"{gain['psnr_render']:.2f} -> repaired {gain['psnr_repaired']:.2f} dB).")
    b = results.get("baseline_3dgs")
    if b is not None:
        notes.append(f"Plain 3DGS for the same training time ({b['train_seconds']:.0f} s, no repair): PSNR "
                     f"{fmt(b['psnr'], 2)} dB, SSIM {fmt(b['ssim'])} "
                     f"(final model: {fmt(results['fine']['psnr'], 2)} dB).")
    if results.get("masks_note"):
        notes.append(results["masks_note"])
    if lpips_note:
        notes.append(f"LPIPS not computed: {lpips_note}")
    contact = ws.output("repair", "contact_sheet")
    masks_sheet, masks = ws.output("scene", "masks_sheet"), None
    if masks_sheet.is_file():
        used = (read_json(ws.output("scene", "info")).get("masks") or {}).get("source") == "auto"
        caption = ("The training photos with their automatic masks' outline (green), used for training." if used
                   else "The automatic masks, not used (see above): the outline they proposed; correct the masks "
                   f"in {ws.output('scene', 'masks_proposed')} and give them back with --masks DIR.")
        masks = (caption, masks_sheet)
    write_report_html(run.output("report_html"), title=f"wgs report: {ws.root.name}", times=stage_times(ws),
                      coarse=results["coarse"], fine=results["fine"], per_fine=per_fine,
                      per_coarse=pers.get("coarse", {}), sheets=sheets, plot=run.path("error_vs_time.png"),
                      contact_sheet=contact if contact.is_file() else None, notes=notes,
                      turntable=run.path("turntable.gif"), outlines=outlines, masks=masks)


def run_eval(ws: Workspace, cfg: EvalConfig, env: StageEnv, force: bool = False) -> bool:
    """Evaluate `env.final` (fine, or coarse when the repair stages were left out) and G_c."""
    return ws.run_stage("eval", cfg, {"final": env.final}, force,
                        lambda run: evaluate(run, ws, cfg, env.device, env.final, env.seed),
                        requires=("scene", "coarse", env.final))


def evaluate(run: StageRun, ws: Workspace, cfg: EvalConfig, device: torch.device, final: str, seed: int) -> str:
    scene = load_prepared(ws.output("scene", "prepared"), load_test_images=True)
    if not scene.test:
        raise InputError("the scene has no test views: nothing to evaluate", ws.stage_dir("scene"))
    frames = scene.test[: cfg.max_views] if cfg.max_views else scene.test
    try:
        lpips_fn, lpips_note = LPIPS(cfg.lpips_net, cfg.lpips_weights).to(device), None
    except LpipsUnavailable as exc:
        lpips_fn, lpips_note = None, str(exc)
        log(f"eval: {exc}")
    bg = background_for(scene)
    t0 = time.perf_counter()
    results, gain, pers = {}, None, {}
    want_gain = cfg.repair_gain and final == "fine" and ws.manifest("finetune") is not None
    repair_gain = None
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
        out = run.path("renders", "x").parent if key == "fine" else None
        outlines = run.path("outlines", "x").parent if key == "fine" else None
        per = evaluate_model(splats, frames, device, bg, lpips_fn, out, on_view=repair_gain, outline_dir=outlines,
                             desc=f"eval {st}" + (" and the repair gain" if repair_gain else ""))
        if key == "fine":
            final_splats = splats  # the turntable renders it again, without a second load
        atomic_write_json(run.path("per_view.json" if key == "fine" else "per_view_coarse.json"), per)
        pers[key] = per
        results[key] = {**summarise(per), "num_gaussians": int(splats["means"].shape[0]),
                        "num_views": len(frames)}
        if repair_gain is not None:
            gain = repair_gain.summary()
            atomic_write_json(run.path("per_view_repair.json"), {"render": repair_gain.before,
                                                                  "repaired": repair_gain.after})
    if ws.status("baseline") == "stale":
        log("eval: the plain-3DGS baseline belongs to earlier stages and is left out (`wgs baseline` trains it again)")
    if ws.status("baseline") == "fresh":
        b = ws.manifest("baseline")
        b_splats, _ = load_checkpoint(ws.output("baseline", "model"), scene.norm, device)
        per = evaluate_model(b_splats, frames, device, bg, lpips_fn, desc="eval baseline")
        results["baseline_3dgs"] = {**summarise(per), "num_gaussians": int(b_splats["means"].shape[0]),
                                    **{k: b[k] for k in ("budget_s", "train_seconds", "iterations")}}
    carved = ws.output("repair", "carved_hull")
    shape = shape_reference(scene, frames, cfg.hull_resolution, load_grid(carved) if carved.is_file() else None)
    if shape is not None:
        per_view = ("hull_test", "carved_hull_test", "leave_one_out")
        atomic_write_json(run.path("per_view_shape.json"), {k: shape.pop(f"{k}_per_view") for k in per_view})
        shape["mirror"] = scene.info.get("mirror")
        shape["own_shape"] = (ws.manifest("repair") or {}).get("own_shape")
    res = {**results["fine"], "final_model": final, "coarse": results["coarse"],
           "baseline_3dgs": results.get("baseline_3dgs"),
           "repair_gain": gain, "shape": shape, "masks_note": masks_note(scene),
           "lpips_net": cfg.lpips_net if lpips_fn else None,
           "lpips_unavailable": lpips_note, "metrics": METRICS_DOC,
           "lpips_weights": lpips_fn.sources if lpips_fn else None,
           "stage_times_s": {r["stage"]: r["wall_time_s"] for r in stage_times(ws)},
           "estimate_s": ws.run_record().get("estimate"), "budget_s": ws.run_record().get("budget_s")}
    source = ((ws.manifest("scene") or {}).get("summary") or {}).get("source")
    res.update({"scene": source, "method": "wgs" if final == "fine" else "wgs-coarse-only",
                "version": __version__, "seed": seed,
                # the nerfstudio `ns-eval` layout, for tools that read it
                "experiment_name": Path(str(source)).name if source else ws.root.name,
                "method_name": "wgs", "checkpoint": str(ws.output(final, "model")),
                "results": {k: results["fine"][k] for k in ("psnr", "psnr_std", "ssim", "ssim_std",
                                                            "lpips", "lpips_std") if k in results["fine"]}})
    # what error_vs_time.png shows: (cumulative s, probe-view PSNR) per training loop
    res["curves"] = curve_points(ws, stage_times(ws), "baseline_3dgs" in results)
    atomic_write_json(run.output("results"), res)
    write_report(run, stage_times(ws), results["coarse"], results["fine"], time.perf_counter() - t0,
                 lpips_note, res["curves"], results.get("baseline_3dgs"), shape, res["masks_note"],
                 (res["estimate_s"] or {}).get("eval"))
    if cfg.turntable_frames > 0:
        write_gif(run.path("turntable.gif"), [render_frame(final_splats, f, device, bg)[0].numpy()
                                              for f in orbit_frames(scene.train, cfg.turntable_frames)])
    write_html(run, ws, frames, bg, pers, {**results, "shape": shape, "masks_note": res["masks_note"]},
               time.perf_counter() - t0, lpips_note, gain)
    run.record.update({"psnr": res["psnr"], "ssim": res["ssim"], "lpips": res["lpips"],
                       "coarse_psnr": results["coarse"]["psnr"]})
    c, f = results["coarse"], results["fine"]
    lines = [f"eval: PSNR {fmt(c['psnr'], 2)} -> {fmt(f['psnr'], 2)} dB, SSIM {fmt(c['ssim'])} -> {fmt(f['ssim'])}, "
             f"LPIPS {fmt(c['lpips'])} -> {fmt(f['lpips'])} (coarse -> fine, {len(frames)} test views)"]
    if results.get("baseline_3dgs") is not None:
        b = results["baseline_3dgs"]
        lines.append(f"eval: plain 3DGS for the same training time ({b['train_seconds']:.0f} s): "
                     f"PSNR {fmt(b['psnr'], 2)} dB, SSIM {fmt(b['ssim'])}")
    if shape is not None:
        lines.append("eval: " + shape_line(c, f, shape))
    if gain is not None:
        lines.append(f"eval: repair gain at the test poses {gain['gain_db']:+.2f} dB (render {gain['psnr_render']:.2f}"
                     f" -> repaired {gain['psnr_repaired']:.2f} dB, {gain['views_improved']}/{gain['num_views']} "
                     "views improved)")
    return "\n".join(lines)

__all__ = ["run_eval"]
