"""The eval stage's scores: per-view PSNR / SSIM / LPIPS and silhouette scores of a model at the
test views, their means, and the repair's own gain at the test poses."""

from __future__ import annotations

import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from ...gaussians.localise import localise
from ...gaussians.trainer import render_frame
from ...io.images import write_png
from ...metrics import psnr, ssim
from ...progress import BAR, progress_bar
from ...scene.dataset import Frame, composite
from ...shape.scores import SILHOUETTE_DOC, silhouette_scores
from ...workspace import Workspace
from ..shared import ensemble_repair, workspace_repairer
from .html import outline_sheet

METRICS_DOC = {
    "psnr": "mean over views of per-view PSNR (dB), images in [0, 1] on the dataset background",
    "ssim": "11x11 Gaussian window, sigma 1.5, zero padding, mean of the map (3DGS / GaussianObject code)",
    "lpips": "LPIPS v0.1 in plain torch from local torchvision-format weights",
    "silhouette": SILHOUETTE_DOC,
}

SILHOUETTE_KEYS = ("iou", "excess", "missed")


def evaluate_model(
    splats,
    frames,
    device,
    bg,
    lpips_fn,
    out_dir=None,
    desc="eval",
    on_view: Callable[[Frame, torch.Tensor, torch.Tensor], None] | None = None,
    outline_dir: Path | None = None,
) -> dict[str, dict[str, float]]:
    """Per-view PSNR / SSIM (/ LPIPS) of `splats` at `frames`, and where a frame has a mask its
    silhouette scores (silhouette_iou, silhouette_excess, silhouette_missed); renders go to
    `out_dir`, outline sheets (`html.outline_sheet`) to `outline_dir`.
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
                    per["lpips"][f.name] = float(
                        lpips_fn(rgb.permute(2, 0, 1)[None].to(device), ref.permute(2, 0, 1)[None].to(device))
                    )
            if out_dir is not None:
                write_png(out_dir / f.name, rgb.numpy())
            if on_view is not None:
                on_view(f, rgb, ref)
            prog.update(BAR, completed=i + 1)
    return {k: v for k, v in per.items() if v}


def localised(splats, frames: list[Frame], bg: torch.Tensor, steps: int) -> tuple[list[Frame], dict[str, Any]]:
    """The test frames with each camera localised on the frozen `splats` (`gaussians.localise`), and
    how far they moved: per view and the median rotation (degrees) and centre shift (as a fraction
    of the camera's distance from the world's centre)."""
    moved, degrees, shifts = [], {}, {}
    with progress_bar(f"eval: localising {len(frames)} test cameras", len(frames)) as prog:
        for i, f in enumerate(frames):
            g, delta = localise(splats, f, bg, steps)
            cos = ((torch.trace(delta[:3, :3]) - 1) / 2).clamp(-1, 1)
            degrees[f.name] = float(torch.rad2deg(torch.arccos(cos)))
            shifts[f.name] = float((g.center - f.center).norm() / f.center.norm().clamp_min(1e-9))
            moved.append(g)
            prog.update(BAR, completed=i + 1)
    return moved, {
        "steps": steps,
        "median_rotation_deg": statistics.median(degrees.values()),
        "median_shift": statistics.median(shifts.values()),
        "rotation_deg": degrees,
        "shift": shifts,
    }


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
        return {
            "psnr_render": statistics.fmean(self.before.values()),
            "psnr_repaired": statistics.fmean(self.after.values()),
            "gain_db": statistics.fmean(gains),
            "gain_std": statistics.pstdev(gains),
            "views_improved": sum(g > 0 for g in gains),
            "num_views": len(gains),
            "prior": self.repairer.meta.prior,
            "ensemble": len(self.members),
        }


def summarise(per: dict[str, dict[str, float]]) -> dict[str, float | None]:
    """Mean and spread over views of each metric (None where it was not measured)."""
    out: dict[str, float | None] = {}
    for m in ("psnr", "ssim", "lpips", *(f"silhouette_{k}" for k in SILHOUETTE_KEYS)):
        vals = list(per.get(m, {}).values())
        out[m] = statistics.fmean(vals) if vals else None
        out[f"{m}_std"] = statistics.pstdev(vals) if vals else None
    return out
