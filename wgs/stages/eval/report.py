"""The eval stage's reports: report.md (error against run time, with the estimate beside each
stage's time), error_vs_time.png, report.html (`html`) and the summary lines it prints."""

from __future__ import annotations

from typing import Any

from ...curves import read_curve
from ...io import atomic_write_bytes, read_json
from ...io.images import write_png
from ...progress import fmt
from ...scene.dataset import composite
from ...shape.scores import SILHOUETTE_DOC
from ...workspace import StageRun, Workspace
from ..shared import stage_times
from .shape import shape_line


def write_report(
    run: StageRun,
    times: list[dict[str, Any]],
    coarse: dict,
    fine: dict,
    eval_s: float,
    lpips_note: str | None,
    curves: dict[str, list[tuple[float, float]]] | None = None,
    baseline: dict | None = None,
    shape: dict | None = None,
    masks_note: str | None = None,
    eval_estimate_s: float | None = None,
) -> None:
    total = (times[-1]["cumulative_s"] if times else 0.0) + eval_s
    lines = [
        "# wgs report: error against run time",
        "",
        "| stage | wall time (s) | estimate (s) | cumulative (s) | peak memory (MiB) | PSNR | SSIM | LPIPS "
        "| silhouette IoU |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in times:
        q = coarse if r["stage"] == "coarse" else fine if r["stage"] == "fine" else None
        qs = (
            [fmt(q["psnr"], 2), fmt(q["ssim"]), fmt(q["lpips"]), fmt(q.get("silhouette_iou"))]
            if q
            else ["", "", "", ""]
        )
        lines.append(
            f"| {r['stage']} | {r['wall_time_s']:.1f} | {fmt(r['estimate_s'], 1, '')} | "
            f"{r['cumulative_s']:.1f} | {fmt(r['peak_memory_mb'], 0)} | " + " | ".join(qs) + " |"
        )
    lines.append(f"| eval | {eval_s:.1f} | {fmt(eval_estimate_s, 1, '')} | {total:.1f} | | | | | |")
    lines += [
        "",
        f"Quality is measured on {views_phrase(fine)} (mean over views; "
        "coarse = G_c, fine = G_f). The estimate is the one printed before training (`wgs.estimate`); "
        "empty where the stage did not run in that `wgs all`.",
        "",
    ]
    after = [r for r in times if r.get("estimate_after_pilots_s") is not None]
    if after:
        modelled, took = sum(r["estimate_after_pilots_s"] for r in after), sum(r["after_pilots_s"] for r in after)
        lines += [
            f"With the plateau the coarse stage's pilots found in place of the expected one, "
            f"{', '.join(r['stage'] for r in after)} were estimated at {modelled:.1f} s once the pilots "
            f"ended (the coarse stage's models, then the stages after it); they took {took:.1f} s "
            f"(estimate / time {modelled / max(took, 1e-9):.2f}).",
            "",
        ]
    for r in times:
        st = r.get("stopping")
        if st and "pilot_iterations" in st:
            lines += [
                f"{r['stage']} stopped at iteration {st['stop_at']}: the held-out PSNR of "
                f"{len(st['pilot_iterations'])} pilots (each photo held out in turn, half size) reached its plateau "
                f"at iteration {st['plateau']} ({st['held_out_psnr']:.2f} dB, best {st['best_psnr']:.2f} dB), and "
                "the models train a margin times that.",
                "",
            ]
        elif st:
            lines += [
                f"{r['stage']} stopped at iteration {st['stop_at']}: {st['margin']:g} times the plateau of the "
                f"coarse stage's pilots (iteration {st['plateau']}).",
                "",
            ]
    if shape is not None:
        lines += [shape_line(coarse, fine, shape) + ".", SILHOUETTE_DOC[0].upper() + SILHOUETTE_DOC[1:] + ".", ""]
    if masks_note:
        lines += [masks_note, ""]
    if lpips_note:
        lines += [f"LPIPS not computed: {lpips_note}", ""]
    atomic_write_bytes(run.output("report"), "\n".join(lines).encode())
    plot_error_vs_time(run.path("error_vs_time.png"), times, coarse, fine, curves, baseline)


def curve_points(
    ws: Workspace, times: list[dict[str, Any]], baseline: bool = False
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


def plot_error_vs_time(
    path, times, coarse, fine, curves: dict[str, list[tuple[float, float]]] | None = None, baseline: dict | None = None
) -> None:
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


def write_html(
    run: StageRun,
    ws: Workspace,
    frames,
    bg,
    pers: dict,
    results: dict,
    eval_s: float,
    lpips_note: str | None,
    gain: dict | None,
) -> None:
    """report.html beside report.md: the same table plus the views and sheets (`html`)."""
    from ...io.images import read_image
    from .html import error_sheet, worst_and_best, write_report_html

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
    for name in sorted(iou, key=lambda n: iou[n])[:3]:
        if (p := run.path("outlines", name)).is_file():
            outlines.append((f"IoU {iou[name]:.3f}", name, p))
    notes = [
        f"Quality on {views_phrase(results['fine'])} (mean over views); coarse = G_c, "
        f"fine = G_f. Evaluation took {eval_s:.0f} s."
    ]
    if results.get("shape") is not None:
        notes.append(shape_line(results["coarse"], results["fine"], results["shape"]) + ".")
    if gain is not None:
        notes.append(
            f"Repair gain at the test poses: {gain['gain_db']:+.2f} dB (G_c render "
            f"{gain['psnr_render']:.2f} -> repaired {gain['psnr_repaired']:.2f} dB)."
        )
    b = results.get("baseline_3dgs")
    if b is not None:
        notes.append(
            f"Plain 3DGS for the same training time ({b['train_seconds']:.0f} s, no repair): PSNR "
            f"{fmt(b['psnr'], 2)} dB, SSIM {fmt(b['ssim'])} "
            f"(final model: {fmt(results['fine']['psnr'], 2)} dB)."
        )
    if results.get("masks_note"):
        notes.append(results["masks_note"])
    if lpips_note:
        notes.append(f"LPIPS not computed: {lpips_note}")
    contact = ws.output("repair", "contact_sheet")
    masks_sheet, masks = ws.output("prepare", "masks_sheet"), None
    if masks_sheet.is_file():
        used = (read_json(ws.output("prepare", "info")).get("masks") or {}).get("source") == "auto"
        caption = (
            "The training photos with their automatic masks' outline (green), used for training."
            if used
            else "The automatic masks, not used (see above): the outline they proposed; correct the masks "
            f"in {ws.output('prepare', 'masks_proposed')} and give them back with --masks DIR."
        )
        masks = (caption, masks_sheet)
    write_report_html(
        run.output("report_html"),
        title=f"wgs report: {ws.root.name}",
        times=stage_times(ws),
        coarse=results["coarse"],
        fine=results["fine"],
        per_fine=per_fine,
        per_coarse=pers.get("coarse", {}),
        sheets=sheets,
        plot=run.path("error_vs_time.png"),
        contact_sheet=contact if contact.is_file() else None,
        notes=notes,
        turntable=run.path("turntable.gif"),
        outlines=outlines,
        masks=masks,
    )


def views_phrase(scores: dict[str, Any]) -> str:
    """'5 test views', or for a scene without test views what its numbers are instead."""
    n = scores.get("num_views")
    if scores.get("views") == "training":
        return f"{n} training views: there are no test views, so this is the fit to the photos, not novel views"
    if scores.get("test_cameras_localised"):
        return f"{n} test views, their cameras localised on the model"
    return f"{n} test views"


def summary_lines(results: dict[str, Any], shape: dict | None, gain: dict | None) -> list[str]:
    """What the stage prints: G_c -> G_f, the baseline, the silhouettes and the repair gain."""
    c, f = results["coarse"], results["fine"]
    lines = [
        f"eval: PSNR {fmt(c['psnr'], 2)} -> {fmt(f['psnr'], 2)} dB, SSIM {fmt(c['ssim'])} -> {fmt(f['ssim'])}, "
        f"LPIPS {fmt(c['lpips'])} -> {fmt(f['lpips'])} (coarse -> fine, {views_phrase(f)})"
    ]
    if results.get("baseline_3dgs") is not None:
        b = results["baseline_3dgs"]
        lines.append(
            f"eval: plain 3DGS for the same training time ({b['train_seconds']:.0f} s): "
            f"PSNR {fmt(b['psnr'], 2)} dB, SSIM {fmt(b['ssim'])}"
        )
    if shape is not None:
        lines.append("eval: " + shape_line(c, f, shape))
    if gain is not None:
        lines.append(
            f"eval: repair gain at the test poses {gain['gain_db']:+.2f} dB (render {gain['psnr_render']:.2f}"
            f" -> repaired {gain['psnr_repaired']:.2f} dB, {gain['views_improved']}/{gain['num_views']} "
            "views improved)"
        )
    return lines
