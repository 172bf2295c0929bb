"""Training of the silhouette model S on corpus pairs: at a novel pose, the coarse model's render
and opacity and the 4-view hull's silhouette and depth in, the exactly rendered true alpha out.

The loss is a binary cross-entropy that costs a missed object pixel `object_weight` times an excess
pixel: carving with S must rather leave the hull fat than cut the object. Whole objects are held
out (`corpus.is_holdout`) and measure S against the hull and the coarse model's own opacity.
"""

from __future__ import annotations

import copy
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from wgs.errors import InputError
from wgs.models.silhouette_net import SilhouetteNet, SilhouetteNetConfig
from wgs.shape.features import predict_batch, silhouette_inputs, to_work_size
from wgs.shape.scores import silhouette_scores
from wgs.training.loop import FitState, MaskTrainConfig, fit

from .train import growing_subsets


@dataclass
class ShapeTrainConfig(MaskTrainConfig):
    net: SilhouetteNetConfig = field(default_factory=SilhouetteNetConfig)
    steps: int = 2500


def load_shape_pairs(pairs_dir: Path, work_size: int) -> dict[str, Any]:
    """The pair files that carry the hull channels, at `work_size`: inputs [N, 6, h, w], target
    [N, h, w] (the true alpha's coverage), holdout [N] bool, object [N] (file index), and names (file
    stems)."""

    xs, ys, hold, obj = [], [], [], []
    names: list[str] = []
    files = sorted(p for p in pairs_dir.glob("*.npz"))
    for f in files:
        with np.load(f) as z:
            if "hull" not in z.files:
                continue
            rgb = torch.from_numpy(z["render"]).float() / 255
            alpha = torch.from_numpy(z["render_alpha"]).float() / 255
            hull = torch.from_numpy(z["hull"]).float() / 255
            depth = torch.from_numpy(z["hull_depth"].astype(np.float32))
            x = torch.stack([silhouette_inputs(rgb[i], alpha[i], hull[i], depth[i]) for i in range(len(rgb))])
            xs.append(to_work_size(x, work_size))
            true = (torch.from_numpy(z["ref_alpha"]).float() / 255 > 0.5).float()
            ys.append(to_work_size(true[:, None], work_size)[:, 0])
            hold.append(torch.full((len(rgb),), bool(z["holdout"])))
            obj.append(torch.full((len(rgb),), len(names)))
            names.append(f.stem)
    if not xs:
        raise InputError(
            "no pair files with hull channels (rebuild them with `python -m tools.prior pairs`)", pairs_dir
        )
    return {
        "inputs": torch.cat(xs),
        "target": torch.cat(ys),
        "holdout": torch.cat(hold),
        "object": torch.cat(obj),
        "names": names,
    }


def augment(x: torch.Tensor, y: torch.Tensor, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The same random flip / transpose of inputs [B, 6, H, W] and targets [B, H, W] (a camera's roll
    and handedness say nothing of shape), and a colour-channel permutation of the render."""
    k = int(torch.randint(0, 8, (1,), generator=gen))
    if k & 1:
        x, y = x.flip(-1), y.flip(-1)
    if k & 2:
        x, y = x.flip(-2), y.flip(-2)
    if k & 4:
        x, y = x.transpose(-1, -2), y.transpose(-1, -2)
    perm = torch.randperm(3, generator=gen)
    return torch.cat([x[:, perm], x[:, 3:]], 1), y


def weighted_bce(logits: torch.Tensor, target: torch.Tensor, object_weight: float) -> torch.Tensor:
    """logits [B, 1, H, W], target [B, H, W]."""
    w = 1.0 + (object_weight - 1.0) * target
    return F.binary_cross_entropy_with_logits(logits[:, 0], target, weight=w)


@torch.no_grad()
def held_out_scores(model: torch.nn.Module, data: dict[str, torch.Tensor], device: torch.device) -> dict[str, float]:
    """Mean silhouette IoU / excess / missed on the held-out pairs of S (p > 0.5), of the hull and of
    the coarse model's opacity (> 0.5)."""
    idx = data["holdout"].nonzero()[:, 0]
    rows: dict[str, list[dict[str, float]]] = {"S": [], "hull": [], "coarse": []}
    for chunk in idx.split(32):
        x = data["inputs"][chunk]
        prob = predict_batch(model, x)
        for j in range(len(chunk)):
            true = data["target"][chunk[j]] > 0.5
            rows["S"].append(silhouette_scores(prob[j] > 0.5, true))
            rows["hull"].append(silhouette_scores(x[j, 4] > 0.5, true))
            rows["coarse"].append(silhouette_scores(x[j, 3] > 0.5, true))
    return {
        f"{who}_{k}": statistics.fmean(r[k] for r in rs)
        for who, rs in rows.items()
        for k in ("iou", "excess", "missed")
    }


def train_silhouette(
    data: dict[str, torch.Tensor],
    cfg: ShapeTrainConfig,
    device: torch.device,
    log=print,
    init: SilhouetteNet | None = None,
) -> tuple[SilhouetteNet, dict]:
    """Train S on the non-held-out pairs (`training.loop`); returns the EMA model and its curve
    (held-out scores at each record)."""
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    model: SilhouetteNet = copy.deepcopy(init) if init is not None else SilhouetteNet(cfg.net)
    model.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    train_idx = (~data["holdout"]).nonzero()[:, 0]
    if train_idx.numel() == 0:
        raise InputError("every pair is held out: nothing to train S on")
    plan = cfg.plan()

    def batch_loss(step: int) -> torch.Tensor:
        pick = train_idx[torch.randint(0, train_idx.numel(), (cfg.batch,), generator=gen)]
        x, y = augment(data["inputs"][pick], data["target"][pick], gen)
        return weighted_bce(model(x.to(device)), y.to(device), cfg.object_weight)

    def report(st: FitState) -> None:
        scores = st.curve["val"][-1] if st.curve["val"] else {}
        log(
            f"S: step {st.step}/{cfg.steps} loss {st.curve['loss'][-1]:.4f} held-out IoU "
            f"S {scores.get('S_iou', float('nan')):.3f} hull {scores.get('hull_iou', float('nan')):.3f} "
            f"coarse {scores.get('coarse_iou', float('nan')):.3f} ({time.perf_counter() - t0:.0f} s)"
        )

    t0 = time.perf_counter()
    evaluate = (lambda m: held_out_scores(m, data, device)) if data["holdout"].any() else None
    ema, st = fit(model, opt, batch_loss, plan, "S", gen=gen, evaluate=evaluate, on_record=report)
    return ema.cpu(), {**st.summary(), "config": asdict(cfg)}


def shape_curve(
    data: dict[str, torch.Tensor], fractions: list[float], cfg: ShapeTrainConfig, device: torch.device, log=print
) -> list[dict]:
    """Held-out IoU of S against corpus size (`train.growing_subsets`)."""
    rows = []
    for row, use in growing_subsets(data["object"], data["holdout"], fractions, cfg.seed):
        _, curve = train_silhouette({k: v[use] for k, v in data.items() if k != "names"}, cfg, device, log)
        rows.append({**row, **curve["val"][-1]})
        log(f"shape curve: {rows[-1]}")
    return rows
