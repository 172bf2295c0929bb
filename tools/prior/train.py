"""Pretraining of the repair prior on corpus pairs: D on the LL subband, U on the HF subbands.

D learns the Difix-style single step: its input is the *render* noised to a low level t < t_max
(not the clean image, as in plain denoising training), its target the ground truth; at repair time
it runs once at t = 0, deterministic. A model trained on noised clean images learns to copy x_t at
low noise and ignores the corrupted control signal, which is why a from-scratch D repaired nothing.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from wgs.errors import InputError
from wgs.io.checkpoint import UnreadableCheckpoint, read_checkpoint, write_checkpoint
from wgs.models.data import random_crops, to_model
from wgs.models.denoiser_meta import DenoiserMeta
from wgs.models.hf_unet import HFUNet, HFUNetConfig
from wgs.models.ll_denoiser import LLDenoiser, LLDenoiserConfig
from wgs.training.denoiser import psnr_model_space, train_denoiser
from wgs.training.hf import identity_l1, train_hf
from wgs.training.loop import FitPlan, FitState
from wgs.wavelet.haar import dwt2


@dataclass
class PriorConfig:
    d_channels: int = 48
    t_max: int = 200  # training noise levels 0..t_max-1 of 1000
    train_timesteps: int = 1000
    d_steps: int = 20000
    d_batch: int = 32
    d_crop: int = 48  # LL pixels
    min_scale: float = 0.7  # zoom augmentation: finer detail than the corpus renders (out) ...
    max_scale: float = 1.6  # ... and larger artifacts (in): scenes are often 200-400 px
    identity_frac: float = 0.2  # share of samples whose input is the truth itself: leave good content alone
    charbonnier: float = 1e-3  # robust L1 (sharper than L2's regression to the mean)
    d_lr: float = 5e-4
    warmup: int = 500  # linear learning-rate warm-up steps, then cosine decay to 0
    ema_decay: float = 0.999
    u_channels: int = 16
    u_steps: int = 6000
    u_batch: int = 32
    u_crop: int = 64  # image pixels
    u_lr: float = 1e-3
    eval_every: int = 500
    seed: int = 0


def load_pack(path: Path) -> dict[str, torch.Tensor]:
    """A training pack (`pack_pairs`): render, ref [N, 3, H, W] in [0, 1], holdout [N] bool, object [N]
    (pair file index)."""
    with np.load(path) as z:
        out = {
            "render": torch.from_numpy(z["render"]).permute(0, 3, 1, 2).float() / 255,
            "ref": torch.from_numpy(z["ref"]).permute(0, 3, 1, 2).float() / 255,
            "holdout": torch.from_numpy(z["holdout"]),
        }
        if "object" in z.files:
            out["object"] = torch.from_numpy(z["object"]).long()
    return out


def growing_subsets(
    objects: torch.Tensor, holdout: torch.Tensor, fractions: list[float], seed: int
) -> Iterator[tuple[dict, torch.Tensor]]:
    """Corpus-size curves: for each fraction, the first fraction of the training objects in a
    fixed random order plus every held-out pair. objects / holdout [N] per pair; yields ({fraction,
    objects, pairs}, the pairs to use [N] bool)."""
    train_objs = objects[~holdout].unique()
    order = train_objs[torch.randperm(len(train_objs), generator=torch.Generator().manual_seed(seed))]
    for frac in fractions:
        keep = order[: max(1, round(frac * len(order)))]
        use = holdout | torch.isin(objects, keep)
        yield {"fraction": frac, "objects": int(len(keep)), "pairs": int((use & ~holdout).sum())}, use


def corpus_curve(pack: Path, fractions: list[float], cfg: PriorConfig, device: torch.device, log=print) -> list[dict]:
    """Held-out gain of D against corpus size (`growing_subsets`)."""
    data = load_pack(pack)
    rows = []
    for row, use in growing_subsets(data["object"], data["holdout"], fractions, cfg.seed):
        _, curve, _ = train_d(cfg, data["render"][use], data["ref"][use], data["holdout"][use], device, log)
        rows.append(
            {
                **row,
                "identity_psnr": curve["val_identity_psnr"],
                "repaired_psnr": curve["val_psnr"][-1],
                "gain_db": curve["val_psnr"][-1] - curve["val_identity_psnr"],
            }
        )
        log(f"curve: {rows[-1]}")
    return rows


def pack_pairs(pairs_dir: Path, out: Path, max_objects: int | None = None) -> dict:
    """All per-object pair files in one compressed pack (what travels to a GPU machine)."""
    files = sorted(pairs_dir.glob("*.npz"))[:max_objects]
    render, ref, hold, names, obj = [], [], [], [], []
    for i, f in enumerate(files):
        with np.load(f) as z:
            render.append(z["render"])
            ref.append(z["ref"])
            hold.append(np.full(len(z["render"]), bool(z["holdout"])))
            obj.append(np.full(len(z["render"]), i, np.int32))
            names.append(f.stem)
    np.savez_compressed(
        out,
        render=np.concatenate(render),
        ref=np.concatenate(ref),
        holdout=np.concatenate(hold),
        object=np.concatenate(obj),
    )
    return {
        "objects": names,
        "pairs": int(sum(len(r) for r in render)),
        "holdout_objects": [n for n, h in zip(names, hold, strict=True) if h[0]],
    }


def augmented_batch(
    render: torch.Tensor,
    ref: torch.Tensor,
    idx: torch.Tensor,
    crop: int,
    scales: tuple[float, float],
    gen: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The same random zoom (log-uniform in `scales`), crop (even offsets: Haar blocks stay
    intact), flips and colour-channel permutation of both images [N, 3, H, W] at idx -> [B, 3, c, c]."""
    lo, hi = math.log(scales[0]), math.log(scales[1])
    s = math.exp(lo + float(torch.rand(1, generator=gen)) * (hi - lo))
    a, b = render[idx], ref[idx]
    if abs(s - 1) > 0.01:
        size = [max(crop, round(a.shape[-2] * s)), max(crop, round(a.shape[-1] * s))]
        a = torch.nn.functional.interpolate(a, size=size, mode="bilinear", align_corners=False, antialias=s < 1)
        b = torch.nn.functional.interpolate(b, size=size, mode="bilinear", align_corners=False, antialias=s < 1)
    perm = torch.randperm(3, generator=gen)
    a, b = random_crops([a[:, perm], b[:, perm]], torch.arange(len(idx)), crop, gen, align=2)
    return a, b


def ll_of(x: torch.Tensor) -> torch.Tensor:
    return to_model(dwt2(x, 1)[0], "wavelet", 1)


class StateFile:
    """The prior's training state in one file, saved at every record and continued from; a state
    of another configuration is refused (`training.loop.LoopCheckpoint`)."""

    def __init__(self, path: Path, config: dict):
        self.path, self.config = path, config

    def load(self) -> dict | None:
        if not self.path.is_file():
            return None
        try:
            saved = read_checkpoint(self.path)
        except UnreadableCheckpoint as exc:
            raise InputError(f"cannot read the training state ({exc}); delete it to start over", self.path) from None
        if saved.get("config") != self.config:
            raise InputError("training state of another configuration; delete it to start over", self.path)
        return saved

    def due(self) -> bool:
        return True

    def save(self, state: dict) -> None:
        write_checkpoint(self.path, {**state, "config": self.config})


PRIOR_D = DenoiserMeta(domain="wavelet", levels=1, start="corrupted", repair_t=0)


def train_d(
    cfg: PriorConfig,
    render: torch.Tensor,
    ref: torch.Tensor,
    hold: torch.Tensor,
    device: torch.device,
    log=print,
    init: LLDenoiser | None = None,
    state_path: Path | None = None,
) -> tuple[LLDenoiser, dict, DenoiserMeta]:
    """D trained on the pairs (`training.denoiser`, from the render); `init`: start from these
    weights (a prior trained on another corpus); `state_path`: the training state saved there
    at every record, and continued from. Returns the EMA model, its curve and its metadata."""
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(cfg.seed)
    meta = dataclasses.replace(PRIOR_D, train_timesteps=cfg.train_timesteps, t_max=cfg.t_max)
    tr, va = (~hold).nonzero()[:, 0], hold.nonzero()[:, 0]
    held = (ll_of(ref[va]).to(device), ll_of(render[va]).to(device))
    identity = psnr_model_space(float((held[1] - held[0]).pow(2).mean()))
    render, ref = render.to(device), ref.to(device)
    model = LLDenoiser(LLDenoiserConfig(3, cfg.d_channels)).to(device)
    if init is not None:
        model.load_state_dict(init.state_dict())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.d_lr, weight_decay=1e-4)
    plan = FitPlan(cfg.d_steps, cfg.d_lr, cfg.eval_every, warmup=cfg.warmup, ema_decay=cfg.ema_decay)

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        idx = tr[torch.randint(len(tr), (cfg.d_batch,), generator=gen)]
        r, c = augmented_batch(render, ref, idx.to(render.device), 2 * cfg.d_crop, (cfg.min_scale, cfg.max_scale), gen)
        same = (torch.rand(len(idx), generator=gen) < cfg.identity_frac).to(r.device)
        r = torch.where(same[:, None, None, None], c, r)
        return ll_of(c), ll_of(r)

    def report(st: FitState) -> None:
        log(
            f"D step {st.step}: loss {st.curve['loss'][-1]:.5f}  held-out LL PSNR {identity:.2f} "
            f"-> {psnr_model_space(st.curve['val'][-1]):.2f} dB  ({time.perf_counter() - t0:.0f} s)"
        )

    model, st = train_denoiser(
        model,
        meta,
        batch,
        plan,
        gen,
        opt,
        held=held,
        charbonnier=cfg.charbonnier,
        name="prior D",
        on_record=report,
        checkpoint=None if state_path is None else StateFile(state_path, asdict(cfg)),
    )
    curve = {**st.summary(), "val_psnr": [psnr_model_space(v) for v in st.curve["val"]], "val_identity_psnr": identity}
    return model, curve, meta


def train_u(
    cfg: PriorConfig,
    render: torch.Tensor,
    ref: torch.Tensor,
    hold: torch.Tensor,
    device: torch.device,
    log=print,
    init: HFUNet | None = None,
) -> tuple[HFUNet, dict]:
    """U trained on the pairs (`training.hf`; from `init`'s weights when given); the best held-out
    state is kept."""
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    tr, va = (~hold).nonzero()[:, 0], hold.nonzero()[:, 0]
    held = (render[va].to(device), ref[va].to(device))
    render, ref = render.to(device), ref.to(device)
    model = HFUNet(HFUNetConfig(channels=cfg.u_channels)).to(device)
    if init is not None:
        model.load_state_dict(init.state_dict())
    opt = torch.optim.Adam(model.parameters(), lr=cfg.u_lr)
    plan = FitPlan(cfg.u_steps, cfg.u_lr, cfg.eval_every, max_norm=None, keep_best=True)

    def batch() -> tuple[torch.Tensor, torch.Tensor]:
        idx = tr[torch.randint(len(tr), (cfg.u_batch,), generator=gen)]
        return augmented_batch(render, ref, idx.to(render.device), cfg.u_crop, (cfg.min_scale, cfg.max_scale), gen)

    identity = identity_l1(*held)
    model, st, _ = train_hf(
        model,
        batch,
        plan,
        gen,
        opt,
        held,
        start_is_bar=init is not None,
        name="prior U",
        on_record=lambda st: log(f"U step {st.step}: held-out HF L1 {identity:.5f} -> {st.curve['val'][-1]:.5f}"),
    )
    return model, {**st.summary(), "identity": identity}


def train_prior(
    pack: Path,
    out: Path,
    cfg: PriorConfig,
    device: torch.device,
    provenance: dict | None = None,
    log=print,
    init: Path | None = None,
    state_dir: Path | None = None,
) -> dict:
    """Train D and U on a pack; write out/D, out/U (config.json + model.safetensors), provenance.json.
    init: a prior folder (D/, U/, provenance.json) to start from; its provenance is kept in ours.
    state_dir: where D's training state is kept between runs (a rerun continues)."""
    from wgs.models.hf_unet import HFUNet
    from wgs.models.ll_denoiser import LLDenoiser
    from wgs.models.storage import load_model_of, save_model

    data = load_pack(pack)
    torch.manual_seed(cfg.seed)
    d_init = u_init = None
    if init is not None:
        d_init, u_init = load_model_of(init / "D", LLDenoiser)[0], load_model_of(init / "U", HFUNet)[0]
        prov = init / "provenance.json"
        provenance = {
            **(provenance or {}),
            "init": {"path": str(init), "provenance": json.loads(prov.read_text()) if prov.is_file() else None},
        }
    t0 = time.perf_counter()
    d, d_curve, meta = train_d(
        cfg,
        data["render"],
        data["ref"],
        data["holdout"],
        device,
        log,
        d_init,
        None if state_dir is None else state_dir / "train_state_D.pt",
    )
    save_model(out / "D", d, meta.to_config())
    t1 = time.perf_counter()
    u, u_curve = train_u(cfg, data["render"], data["ref"], data["holdout"], device, log, u_init)
    save_model(out / "U", u)
    record = {
        "config": asdict(cfg),
        "pairs": int(len(data["holdout"])),
        "holdout_pairs": int(data["holdout"].sum()),
        "device": str(device),
        "d_seconds": round(t1 - t0, 1),
        "u_seconds": round(time.perf_counter() - t1, 1),
        "D": d_curve,
        "U": u_curve,
        **(provenance or {}),
    }
    (out / "provenance.json").write_text(json.dumps(record, indent=1))
    return record
