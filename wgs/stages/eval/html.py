"""`6_eval/report.html`: one self-contained page (images embedded as data URIs) with the summary
table, the error-against-time plot, per-view metrics worst first, render | truth | error sheets of
the worst and best views, outline sheets of the worst silhouettes, a turntable GIF and the repair
stage's contact sheet."""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ...io import atomic_write_bytes
from ...progress import fmt

STYLE = """body{font:14px system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}img{max-width:100%;image-rendering:pixelated}
.scroll{max-height:420px;overflow-y:auto;display:inline-block}.note{color:#666}"""


def png_data_uri(path: Path) -> str | None:
    kind = "gif" if path.suffix.lower() == ".gif" else "png"
    return f"data:image/{kind};base64,{base64.b64encode(path.read_bytes()).decode()}" if path.is_file() else None


def error_sheet(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """render | truth | |error| x 4 (clipped), side by side: [H, 3W, 3] in [0, 1]."""
    err = np.clip(np.abs(render - truth) * 4.0, 0.0, 1.0)
    return np.concatenate([render, truth, err], axis=1)


def outline_sheet(render: np.ndarray, true: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """The render [H, W, 3] with its silhouette `pred` [H, W] bool against the true one `true`:
    area the model has too much tinted red, area it misses tinted blue, the true outline green."""
    out = render.copy()
    out[pred & ~true] = 0.4 * out[pred & ~true] + 0.6 * np.array([1.0, 0.0, 0.0])
    out[true & ~pred] = 0.4 * out[true & ~pred] + 0.6 * np.array([0.0, 0.3, 1.0])
    pad = np.pad(true, 1, mode="edge")
    rim = true & ~(pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:])
    out[rim] = np.array([0.0, 0.8, 0.0])
    return out


def worst_and_best(psnr: dict[str, float], k: int = 3) -> list[tuple[str, str]]:
    """[(label, view name)] for the k worst and k best views by PSNR (fewer when there are few views)."""
    order = sorted(psnr, key=lambda name: psnr[name])
    k = min(k, len(order) // 2) if len(order) > 1 else len(order)
    return [("worst", n) for n in order[:k]] + [("best", n) for n in order[::-1][:k]]


def _table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_report_html(
    path: Path,
    *,
    title: str,
    times: list[dict[str, Any]],
    coarse: dict,
    fine: dict,
    per_fine: dict[str, dict[str, float]],
    per_coarse: dict[str, dict[str, float]],
    sheets: list[tuple[str, str, Path]],
    plot: Path,
    contact_sheet: Path | None,
    notes: list[str],
    turntable: Path | None = None,
    outlines: Sequence[tuple[str, str, Path]] = (),
    masks: tuple[str, Path] | None = None,
) -> None:
    """Write the page. sheets: (label, view name, PNG of `error_sheet`) per shown view; outlines the
    same of `outline_sheet`; masks: (caption, contact sheet of the automatic masks)."""
    parts = [
        f"<!doctype html><meta charset='utf-8'><title>{html.escape(title)}</title><style>{STYLE}</style>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    rows = []
    for r in times:
        q = coarse if r["stage"] == "coarse" else fine if r["stage"] == "fine" else None
        rows.append(
            [
                r["stage"],
                f"{r['wall_time_s']:.1f}",
                fmt(r.get("estimate_s"), 1, ""),
                f"{r['cumulative_s']:.1f}",
                fmt(q["psnr"], 2) if q else "",
                fmt(q["ssim"]) if q else "",
                fmt(q["lpips"]) if q else "",
            ]
        )
    parts += [
        "<h2>Summary</h2>",
        _table(["stage", "wall time (s)", "estimate (s)", "cumulative (s)", "PSNR", "SSIM", "LPIPS"], rows),
    ]
    parts += [f"<p class='note'>{html.escape(n)}</p>" for n in notes]
    if turntable is not None and (uri := png_data_uri(turntable)) is not None:
        parts += ["<h2>Turntable of the final model</h2>", f"<img src='{uri}' alt='turntable'>"]
    if (uri := png_data_uri(plot)) is not None:
        parts += ["<h2>Error against run time</h2>", f"<img src='{uri}' alt='error against run time'>"]
    if sheets:
        parts.append("<h2>Worst and best test views</h2><p class='note'>render | ground truth | error x 4</p>")
        for label, name, p in sheets:
            if (uri := png_data_uri(p)) is not None:
                parts.append(
                    f"<h3>{label}: {html.escape(name)} ({fmt(per_fine['psnr'].get(name), 2)} dB)</h3>"
                    f"<img src='{uri}' alt='{html.escape(name)}'>"
                )
    if outlines:
        parts.append(
            "<h2>Silhouettes, worst first</h2><p class='note'>final model's render; red: area it has "
            "too much, blue: area it misses, green: the true outline</p>"
        )
        for label, name, p in outlines:
            if (uri := png_data_uri(p)) is not None:
                parts.append(f"<h3>{html.escape(name)} ({label})</h3><img src='{uri}' alt='{html.escape(name)}'>")
    names = sorted(per_fine["psnr"], key=lambda n: per_fine["psnr"][n])
    extra = [k for k in ("lpips", "silhouette_iou") if k in per_fine]
    rows = [
        [
            n,
            fmt(per_fine["psnr"][n], 2),
            fmt(per_coarse.get("psnr", {}).get(n), 2),
            fmt(per_fine["psnr"][n] - per_coarse["psnr"][n], 2) if n in per_coarse.get("psnr", {}) else "",
            fmt(per_fine["ssim"][n]),
        ]
        + [fmt(per_fine[k].get(n)) for k in extra]
        for n in names
    ]
    parts += [
        "<h2>Per view, worst first</h2>",
        "<div class='scroll'>",
        _table(
            ["view", "PSNR", "coarse PSNR", "gain", "SSIM"]
            + [{"lpips": "LPIPS", "silhouette_iou": "silhouette IoU"}[k] for k in extra],
            rows,
        ),
        "</div>",
    ]
    if masks is not None and (uri := png_data_uri(masks[1])) is not None:
        parts += [
            "<h2>Automatic masks</h2>",
            f"<p class='note'>{html.escape(masks[0])}</p>",
            f"<img src='{uri}' alt='automatic masks'>",
        ]
    if contact_sheet is not None and (uri := png_data_uri(contact_sheet)) is not None:
        parts += [
            "<h2>Repair: pseudo references</h2><p class='note'>coarse render | repaired</p>",
            f"<img src='{uri}' alt='repair contact sheet'>",
        ]
    atomic_write_bytes(path, ("\n".join(parts) + "\n").encode("utf-8"))
