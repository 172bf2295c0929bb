"""Quality against training time: a probe on a fixed few test views for the training loops, and
the `curve.json` each training stage writes (plotted by eval against cumulative wall time)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from .gaussians.callbacks import Probe
from .gaussians.trainer import TrainResult, render_frame
from .io import atomic_write_json, read_json
from .metrics import psnr, ssim
from .scene.dataset import PreparedScene, composite, load_frame_images
from .workspace import Workspace


def probe_views(test_names: list[str], k: int) -> list[int]:
    """k test views spread evenly over the list (all when there are fewer)."""
    n = len(test_names)
    if k <= 0 or n == 0:
        return []
    k = min(k, n)
    return sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(k)})


def test_probe(
    ws: Workspace, scene: PreparedScene, cfg, background: torch.Tensor, device: torch.device
) -> tuple[Probe | None, list[str]]:
    """Mean PSNR / SSIM of the splats on `cfg.curve_views` test views, and their names, every
    `cfg.curve_every_s` training seconds and at least `cfg.curve_points` times over the iterations
    (not under a time budget); (None, []) when the scene has no test views or the curve is off.
    `cfg`: a training config with CurveConfig's fields."""
    every_s, k = cfg.curve_every_s, cfg.curve_views
    ids = probe_views([f.name for f in scene.test], k) if every_s > 0 else []
    if not ids:
        return None, []
    frames = load_frame_images(ws.output("prepare", "prepared"), [scene.test[i] for i in ids])
    refs = [composite(f.pixels, f.mask, background) for f in frames]

    def fn(splats) -> dict[str, float]:
        ps, ss = [], []
        for f, ref in zip(frames, refs, strict=True):
            rgb, _ = render_frame(splats, f, device, background)
            ps.append(psnr(rgb, ref))
            ss.append(ssim(rgb, ref))
        return {"psnr": sum(ps) / len(ps), "ssim": sum(ss) / len(ss)}

    every_it = cfg.iterations // cfg.curve_points if cfg.curve_points > 0 and not cfg.max_seconds else 0
    return Probe(fn, every_s, max(every_it, 1) if every_it else 0), [f.name for f in frames]


def write_curve(path: Path, res: TrainResult, views: list[str]) -> None:
    atomic_write_json(path, {"views": views, "probe_seconds": round(res.probe_seconds, 2), "points": res.curve})


def read_curve(path: Path) -> dict[str, Any] | None:
    return read_json(path) if path.is_file() else None
