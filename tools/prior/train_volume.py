"""Training of the volume model V on corpus volume pairs (`prior.volume_pairs`): the strict hull of
a few views and its mask depths in, the hull of all the object's views out.

The loss is a binary cross-entropy over the cells of the strict hull (outside it the answer is
known) that costs a missed object cell `object_weight` times an excess cell. Whole objects are held
out (`corpus.is_holdout`) and measure V against the strict hull (3D IoU with the many-view hull).
"""

from __future__ import annotations

import copy
import fnmatch
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from wgs.errors import InputError
from wgs.models.volume_net import VolumeNet, VolumeNetConfig
from wgs.training.loop import FitState, MaskTrainConfig, fit


@dataclass
class VolumeTrainConfig(MaskTrainConfig):
    net: VolumeNetConfig = field(default_factory=VolumeNetConfig)
    batch: int = 6  # a 3D step costs more than a 2D one


def load_volume_pairs(pairs_dir: Path, exclude: tuple[str, ...] = ()) -> dict:
    """x [N, 4, R, R, R], y [N, R, R, R], holdout [N] bool, names (file stems kept). `exclude`:
    shell patterns of object names left out entirely (for example shapes a benchmark measures)."""
    xs, ys, hold, names = [], [], [], []
    for f in sorted(pairs_dir.glob("*.npz")):
        if f.name.endswith(".tmp.npz") or any(fnmatch.fnmatch(f.stem, p) for p in exclude):
            continue
        with np.load(f) as z:
            xs.append(torch.from_numpy(z["x"].astype(np.float32)))
            ys.append(torch.from_numpy(z["y"].astype(np.float32)))
            hold.append(torch.full((len(z["x"]),), bool(z["holdout"])))
        names.append(f.stem)
    if not xs:
        raise InputError("no volume pairs (build them with `python -m tools.prior volume-pairs`)", pairs_dir)
    return {"x": torch.cat(xs), "y": torch.cat(ys), "holdout": torch.cat(hold), "names": names}


def augment(x: torch.Tensor, y: torch.Tensor, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """One of the cube's 48 symmetries on inputs [B, C, R, R, R] and targets [B, R, R, R]: the
    channels are scalars, so a turned or mirrored scene is another valid pair."""
    perm = torch.randperm(3, generator=gen).tolist()
    x, y = x.permute(0, 1, *[2 + p for p in perm]), y.permute(0, *[1 + p for p in perm])
    flips = [a for a in range(3) if int(torch.randint(0, 2, (1,), generator=gen))]
    if flips:
        x, y = x.flip([2 + a for a in flips]), y.flip([1 + a for a in flips])
    return x.contiguous(), y.contiguous()


def hull_bce(logits: torch.Tensor, x: torch.Tensor, y: torch.Tensor, object_weight: float) -> torch.Tensor:
    """logits [B, 1, R, R, R] against y [B, R, R, R] over the strict hull's cells (x[:, 0])."""
    inside = x[:, 0] > 0.5
    w = (1.0 + (object_weight - 1.0) * y) * inside
    return F.binary_cross_entropy_with_logits(logits[:, 0], y, weight=w, reduction="sum") / inside.sum().clamp_min(1)


@torch.no_grad()
def held_out_scores(
    model: torch.nn.Module, data: dict, device: torch.device, keep_above: float = 0.5
) -> dict[str, float]:
    """3D IoU with the many-view hull of the strict hull and of what V keeps (p >= keep_above), the
    share of the excess V removes and of the object it loses."""
    idx = data["holdout"].nonzero()[:, 0]
    inter = {"hull": 0.0, "V": 0.0}
    union = {"hull": 0.0, "V": 0.0}
    lost = excess = cut = true_total = 0.0
    for chunk in idx.split(16):
        x, y = data["x"][chunk], data["y"][chunk] > 0.5
        hull = x[:, 0] > 0.5
        keep = hull & (torch.sigmoid(model(x.to(device)))[:, 0].cpu() >= keep_above)
        for who, m in (("hull", hull), ("V", keep)):
            inter[who] += float((m & y).sum())
            union[who] += float((m | y).sum())
        lost += float((y & ~keep).sum())
        true_total += float(y.sum())
        excess += float((hull & ~y).sum())
        cut += float((hull & ~y & ~keep).sum())
    return {
        "hull_iou": inter["hull"] / max(union["hull"], 1),
        "V_iou": inter["V"] / max(union["V"], 1),
        "excess_cut": cut / max(excess, 1),
        "object_lost": lost / max(true_total, 1),
    }


def train_volume(data: dict, cfg: VolumeTrainConfig, device: torch.device, log=print) -> tuple[VolumeNet, dict]:
    """Train V on the non-held-out pairs (`training.loop`); returns the EMA model and its curve."""
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    model = VolumeNet(cfg.net).to(device=device, memory_format=torch.channels_last_3d)  # type: ignore[call-overload]
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    train_idx = (~data["holdout"]).nonzero()[:, 0]
    if train_idx.numel() == 0:
        raise InputError("every volume pair is held out: nothing to train V on")
    plan = cfg.plan()

    def batch_loss(step: int) -> torch.Tensor:
        pick = train_idx[torch.randint(0, train_idx.numel(), (cfg.batch,), generator=gen)]
        x, y = augment(data["x"][pick], data["y"][pick], gen)
        x, y = x.to(device), y.to(device)
        return hull_bce(model(x), x, y, cfg.object_weight)

    def report(st: FitState) -> None:
        s = st.curve["val"][-1] if st.curve["val"] else {}
        log(
            f"V: step {st.step}/{cfg.steps} loss {st.curve['loss'][-1]:.4f} held-out 3D IoU "
            f"V {s.get('V_iou', float('nan')):.3f} hull {s.get('hull_iou', float('nan')):.3f}, excess cut "
            f"{s.get('excess_cut', float('nan')):.3f}, object lost {s.get('object_lost', float('nan')):.3f} "
            f"({time.perf_counter() - t0:.0f} s)"
        )

    t0 = time.perf_counter()
    evaluate = (lambda m: held_out_scores(m, data, device)) if data["holdout"].any() else None
    ema, st = fit(model, opt, batch_loss, plan, "V", gen=gen, evaluate=evaluate, on_record=report)
    return copy.deepcopy(ema).cpu().eval(), {**st.summary(), "config": asdict(cfg)}
