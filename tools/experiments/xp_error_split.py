"""Where a model's error lies at the test views, against the true masks: the share of the squared
error outside the true silhouette (where the rendered opacity is above and below 0.5) and within
2 px of its outline; PSNR with the error outside the silhouette removed, and with the error outside
the rendered-and-true silhouettes removed; excess and missed area by distance from the outline;
pixels of intermediate opacity (0.1-0.9) per 100 object pixels, rendered and true.

    python xp_error_split.py WORKSPACE [STAGE] [EVERY]

STAGE: fine (default) or coarse; EVERY: score every k-th test view (default 2).
"""

import math
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from wgs.gaussians.splats import load_checkpoint
from wgs.gaussians.trainer import render_frame
from wgs.scene.dataset import composite, load_prepared
from wgs.stages.shared import background_for
from wgs.workspace import Workspace

BINS = 7  # distance bins of 1 px; the last holds everything farther


def psnr_of(err: torch.Tensor) -> float:
    return -10.0 * math.log10(max(float(err.mean()), 1e-12))


if __name__ == "__main__":
    ws = Workspace(Path(sys.argv[1]))
    stage = sys.argv[2] if len(sys.argv) > 2 else "fine"
    every = int(sys.argv[3]) if len(sys.argv) > 3 else 2
    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    bg, dev = background_for(scene), torch.device("cpu")
    splats, _ = load_checkpoint(ws.output(stage, "model"), scene.norm, dev)
    rows: dict[str, list[float]] = {
        k: [] for k in ("psnr", "no_excess", "no_shape_error", "outside_opaque", "outside_faint", "near_outline")
    }
    excess, missed, soft_render, soft_true, area = np.zeros(BINS + 1), np.zeros(BINS + 1), 0, 0, 0
    for f in scene.test[::every]:
        rgb, alpha = render_frame(splats, f, dev, bg)
        err = ((rgb - composite(f.image, f.mask, bg)) ** 2).sum(-1)
        true, pred = f.mask > 0.5, alpha[..., 0] > 0.5
        rows["psnr"].append(psnr_of(err / 3))
        rows["no_excess"].append(psnr_of(torch.where(true, err, 0.0) / 3))
        rows["no_shape_error"].append(psnr_of(torch.where(true & pred, err, 0.0) / 3))
        total = float(err.sum())
        rows["outside_opaque"].append(float(err[~true & pred].sum()) / total)
        rows["outside_faint"].append(float(err[~true & ~pred].sum()) / total)
        d_out = distance_transform_edt(~true.numpy())
        d_in = distance_transform_edt(true.numpy())
        rows["near_outline"].append(float(err.numpy()[(d_out <= 2) & (d_in <= 2)].sum()) / total)
        bins = lambda d: np.bincount(np.minimum(np.ceil(d).astype(int), BINS), minlength=BINS + 1)  # noqa: E731
        excess += bins(d_out[(pred & ~true).numpy()])
        missed += bins(d_in[(true & ~pred).numpy()])
        a = alpha[..., 0]
        soft_render += int(((a > 0.1) & (a < 0.9)).sum())
        soft_true += int(((f.mask > 0.1) & (f.mask < 0.9)).sum())
        area += int(true.sum())
    for k, v in rows.items():
        print(f"{k}: {sum(v) / len(v):.4f}")
    print("excess by distance 1..7+ px (% of the true area):", np.round(100 * excess[1:] / area, 2).tolist())
    print("missed by depth 1..7+ px (% of the true area):", np.round(100 * missed[1:] / area, 2).tolist())
    print(
        f"intermediate opacity per 100 object pixels: rendered {100 * soft_render / area:.2f}, "
        f"true {100 * soft_true / area:.2f}"
    )
