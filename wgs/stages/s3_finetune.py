"""Stage 3: train the repair diffusion model D (LL subband, or RGB for the ablation) and the HF
U-Net U (early stopping), each saved as config.json + model.safetensors under `3_finetune/`."""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

import torch

from ..config import INDEX, FinetuneConfig
from ..errors import InputError
from ..io import atomic_write_json, read_json
from ..io.exr import read_subbands
from ..metrics import psnr
from ..models.data import hwc, load_pairs, random_crops
from ..models.hf_unet import HFUNet, HFUNetConfig
from ..models.ll_denoiser import LLDenoiser, LLDenoiserConfig
from ..models.optim import clipped_step
from ..models.sampling import sdedit_repair, single_step
from ..models.scheduler import DDIMScheduler
from ..models.storage import load_model, save_model
from ..prior import WEIGHTS as PRIOR_WEIGHTS
from ..progress import progress_bar
from ..resume import Checkpointer, check_interrupt, deferred_sigint, rng_state, set_rng_state
from ..threads import adapt as adapt_threads
from ..wavelet.haar import dwt2, idwt2, stack_highs
from ..workspace import StageRun, Workspace


def split_holdout(n: int, frac: float, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    perm = torch.randperm(n, generator=gen)
    k = min(n - 1, max(1, round(frac * n))) if n > 1 else 0
    return perm[k:], perm[:k]


def train_denoiser(cfg: FinetuneConfig, clean: torch.Tensor, bad: torch.Tensor, device: torch.device,
                   gen: torch.Generator, checkpoint: Checkpointer | None = None
                   ) -> tuple[LLDenoiser, dict[str, list[float]]]:
    """Denoising training (sample prediction, MSE to the clean crop) on random crops of (clean,
    corrupted) pairs [P, 3, h, w]; returns the EMA weights."""
    model = LLDenoiser(LLDenoiserConfig(3, cfg.d_channels)).to(device)
    ema = copy.deepcopy(model).eval()
    sched = DDIMScheduler(cfg.train_timesteps)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.d_lr, weight_decay=0.0)
    curve: dict[str, list[float]] = {"step": [], "loss": []}
    acc, done = 0.0, 0
    if checkpoint is not None and (saved := checkpoint.load()) is not None:
        model.load_state_dict(saved["model"])
        ema.load_state_dict(saved["ema"])
        opt.load_state_dict(saved["opt"])
        gen.set_state(saved["generator"])
        set_rng_state(saved["rng"])
        curve, acc, done = saved["curve"], saved["acc"], saved["step"]

    def snapshot() -> dict[str, Any]:
        return {"model": model.state_dict(), "ema": ema.state_dict(), "opt": opt.state_dict(),
                "generator": gen.get_state(), "rng": rng_state(), "curve": curve, "acc": acc, "step": step}

    step = done
    with progress_bar("finetune D", cfg.d_steps) as prog, deferred_sigint():
        prog.update(0, completed=done)
        for step in range(done + 1, cfg.d_steps + 1):
            adapt_threads()
            idx = torch.randint(clean.shape[0], (cfg.d_batch,), generator=gen)
            x0, c = (t.to(device) for t in random_crops([clean, bad], idx, cfg.d_crop, gen))
            t = torch.randint(cfg.train_timesteps, (x0.shape[0],), generator=gen)
            noise = torch.randn(x0.shape, generator=gen).to(device)
            loss = torch.nn.functional.mse_loss(model(sched.add_noise(x0, noise, t), t.to(device), c), x0)
            acc += clipped_step(opt, model, loss, "finetune D", step, ema, cfg.ema_decay)
            if step % 25 == 0 or step == cfg.d_steps:
                n = 25 if step % 25 == 0 else step % 25
                curve["step"].append(step)
                curve["loss"].append(acc / n)
                acc = 0.0
                prog.update(0, completed=step, status=f"loss {curve['loss'][-1]:.4f}")
            if checkpoint is not None and (step == cfg.d_steps or checkpoint.due()):
                checkpoint.save(snapshot())
            check_interrupt("finetune D", step, checkpoint, snapshot)
    return ema, curve


def load_hf_data(ws: Workspace) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """Coarse renders and references of the training views as images [V, 3, H, W] (from their subbands)."""
    index = read_json(ws.stage_dir("mask_data") / INDEX)
    renders, refs, names = [], [], []
    for p in index["hf_pairs"]:
        imgs = []
        for key in ("render", "ref"):
            b = read_subbands(ws.root / p[key])
            ll = hwc(b["LL"])[None]
            hi = [(hwc(b["LH"])[None], hwc(b["HL"])[None], hwc(b["HH"])[None])]
            imgs.append(idwt2(ll, hi)[0])
        renders.append(imgs[0])
        refs.append(imgs[1])
        names.append(p["view"])
    return torch.stack(renders), torch.stack(refs), names


def hf_batch(render: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images [B, 3, H, W] -> corrupted HF [B, 9, h, w], corrupted LL context, reference HF."""
    ll_c, [h_c] = dwt2(render, 1)
    _, [h_r] = dwt2(ref, 1)
    return stack_highs(h_c), ll_c, stack_highs(h_r)


def train_hf_unet(cfg: FinetuneConfig, renders: torch.Tensor, refs: torch.Tensor, device: torch.device,
                  gen: torch.Generator, checkpoint: Checkpointer | None = None, init: HFUNet | None = None
                  ) -> tuple[HFUNet, dict[str, Any]]:
    """L1 on HF subbands of augmented crops; early stopping on held-out crops (a held-out view when
    there are 3 or more, else fixed crops). init: start from these weights (the prior's U).
    The bar is the better of the starting model and no repair at all (identity): an evaluation
    that does not beat it counts toward the patience, so a U that cannot beat the identity stops
    early, and curve["beats_identity"] tells the caller to leave it out."""
    n = renders.shape[0]
    val_ids = torch.tensor([n - 1]) if n >= 3 else torch.arange(n)
    train_ids = torch.arange(n - 1) if n >= 3 else torch.arange(n)
    vgen = torch.Generator().manual_seed(1234)
    val = random_crops([renders, refs], val_ids.repeat(8), 2 * cfg.u_crop, vgen, align=2)
    v_hc, v_ll, v_hr = (t.to(device) for t in hf_batch(*val))
    model = (init if init is not None else HFUNet(HFUNetConfig(channels=cfg.u_channels))).to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.u_lr if init is None else cfg.u_lr * 0.1)
    with torch.no_grad():
        identity = (v_hc - v_hr).abs().mean().item()
        start = (model(v_hc, v_ll) - v_hr).abs().mean().item()
    st: dict[str, Any] = {"curve": {"step": [], "train": [], "val": []}, "best": min(start, identity),
                          "best_state": copy.deepcopy(model.state_dict()), "bad_evals": 0,
                          "stopped": cfg.u_max_steps, "acc": 0.0, "step": 0, "finished": False}
    if checkpoint is not None and (saved := checkpoint.load()) is not None:
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["opt"])
        gen.set_state(saved["generator"])
        set_rng_state(saved["rng"])
        st = saved["loop"]

    def snapshot() -> dict[str, Any]:
        return {"model": model.state_dict(), "opt": opt.state_dict(), "generator": gen.get_state(),
                "rng": rng_state(), "loop": st}

    curve = st["curve"]
    last = st["step"] if st["finished"] else cfg.u_max_steps
    with progress_bar("finetune U", cfg.u_max_steps) as prog, deferred_sigint():
        for step in range(st["step"] + 1, last + 1):
            adapt_threads()
            idx = train_ids[torch.randint(len(train_ids), (cfg.u_batch,), generator=gen)]
            hc, ll, hr = (t.to(device) for t in hf_batch(*random_crops([renders, refs], idx, 2 * cfg.u_crop, gen,
                                                                         align=2)))
            loss = (model(hc, ll) - hr).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            st["acc"] += loss.item()
            st["step"] = step
            if step % cfg.u_eval_every == 0:
                with torch.no_grad():
                    vl = (model(v_hc, v_ll) - v_hr).abs().mean().item()
                curve["step"].append(step)
                curve["train"].append(st["acc"] / cfg.u_eval_every)
                curve["val"].append(vl)
                st["acc"] = 0.0
                prog.update(0, completed=step, status=f"val L1 {vl:.5f}")
                if vl < st["best"] - 1e-7:
                    st["best"], st["best_state"], st["bad_evals"] = vl, copy.deepcopy(model.state_dict()), 0
                else:
                    st["bad_evals"] += 1
                    if st["bad_evals"] >= cfg.u_patience:
                        st["stopped"] = step
            st["finished"] = step == cfg.u_max_steps or st["stopped"] == step
            if checkpoint is not None and (st["finished"] or checkpoint.due()):
                checkpoint.save(snapshot())
            if st["finished"]:
                break
            check_interrupt("finetune U", step, checkpoint, snapshot)
    model.load_state_dict(st["best_state"])
    curve.update({"best_val": st["best"], "identity_val": identity, "start_val": start, "stopped_at": st["stopped"],
                  "beats_identity": st["best"] < identity})
    return model.eval(), curve


def prior_folder(cfg: FinetuneConfig) -> Path | None:
    """Where the pretrained D and U come from: the shipped prior, a folder, or none (from scratch).
    Only the LL-domain embedded D at one Haar level has a prior."""
    if cfg.prior == "none" or cfg.domain != "wavelet" or cfg.levels != 1 or cfg.diffusion != "embedded":
        return None
    return PRIOR_WEIGHTS if cfg.prior == "builtin" else Path(cfg.prior)


def finetune_prior_d(cfg: FinetuneConfig, prior: Path, clean: torch.Tensor, bad: torch.Tensor,
                     held_clean: torch.Tensor, held_bad: torch.Tensor, device: torch.device, gen: torch.Generator
                     ) -> tuple[LLDenoiser, dict[str, Any], dict[str, Any]]:
    """The prior's D adapted to this object's pairs with its own objective (from the noised
    render), early-stopped on the held-out pairs; the prior itself wins unless a step beats it."""
    model, d_cfg = load_model(prior / "D", device)
    if d_cfg.get("start") != "corrupted" or "t_max" not in d_cfg:
        raise InputError("not a repair prior (its config lacks start = corrupted and t_max)",
                         prior / "D" / "config.json")
    sched = DDIMScheduler(d_cfg.get("train_timesteps", 1000))
    held_clean, held_bad = held_clean.to(device), held_bad.to(device)

    def val() -> float:
        model.eval()
        with torch.no_grad():
            out = single_step(model, sched, held_bad, d_cfg.get("repair_t", 0))
        model.train()
        return float((out - held_clean).pow(2).mean())

    opt = torch.optim.AdamW(model.parameters(), lr=cfg.prior_lr, weight_decay=0.0)
    best = start = val()
    best_state, bad_evals, stopped = copy.deepcopy(model.state_dict()), 0, cfg.prior_steps
    curve: dict[str, Any] = {"step": [0], "loss": [], "val": [start]}
    with progress_bar("finetune D (prior)", cfg.prior_steps) as prog:
        for step in range(1, cfg.prior_steps + 1):
            adapt_threads()
            idx = torch.randint(clean.shape[0], (cfg.d_batch,), generator=gen)
            x0, c = (t.to(device) for t in random_crops([clean, bad], idx, cfg.d_crop, gen))
            t = torch.randint(d_cfg["t_max"], (x0.shape[0],), generator=gen)
            noise = torch.randn(c.shape, generator=gen).to(device)
            loss = torch.nn.functional.mse_loss(model(sched.add_noise(c, noise, t), t.to(device), c), x0)
            curve["loss"].append(clipped_step(opt, model, loss, "finetune D", step))
            if step % cfg.prior_eval_every == 0:
                v = val()
                curve["step"].append(step)
                curve["val"].append(v)
                prog.update(0, completed=step, status=f"held-out MSE {v:.5f} (prior {start:.5f})")
                if v < best - 1e-9:
                    best, best_state, bad_evals = v, copy.deepcopy(model.state_dict()), 0
                else:
                    bad_evals += 1
                    if bad_evals >= cfg.prior_patience:
                        stopped = step
                        break
    model.load_state_dict(best_state)
    curve.update({"prior_val": start, "best_val": best, "stopped_at": stopped})
    extra = {k: d_cfg[k] for k in ("domain", "levels", "train_timesteps", "start", "t_max", "repair_t") if k in d_cfg}
    return model.eval(), {**extra, "prior": str(prior)}, curve


def heldout_check(cfg: FinetuneConfig, model: LLDenoiser, d_cfg: dict[str, Any], clean: torch.Tensor,
                  bad: torch.Tensor, device: torch.device) -> dict[str, float]:
    """Error of held-out corrupted samples against the clean ones, before and after D's repair
    (the way `wgs repair` runs this D)."""
    sched = DDIMScheduler(d_cfg.get("train_timesteps", cfg.train_timesteps))
    with torch.no_grad():
        if d_cfg.get("start") == "corrupted":
            rep = single_step(model, sched, bad.to(device), d_cfg.get("repair_t", 0)).cpu()
        else:
            rep = sdedit_repair(model, sched, bad.to(device), cfg.eval_strength, cfg.eval_steps,
                                torch.Generator().manual_seed(0)).cpu()
    scale = 2.0  # model space [-1, 1] spans a range of 2
    return {"num_samples": int(clean.shape[0]),
            "l1_before": float((bad - clean).abs().mean()), "l1_after": float((rep - clean).abs().mean()),
            "psnr_before": psnr(bad, clean, scale), "psnr_after": psnr(rep.clamp(-1, 1), clean, scale)}


def plot_curves(path, curves: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    d = curves["D"]
    if "prior_val" in d:  # a fine-tuned prior: its held-out error, step 0 = the prior as shipped
        axes[0].plot(d["step"], d["val"], label="held-out")
        axes[0].set(title="D from the prior (held-out MSE)", xlabel="step")
    else:
        axes[0].plot(d["step"], d["loss"])
        axes[0].set(title="D (clean-image MSE)", xlabel="step", yscale="log")
    if "U" in curves:
        u = curves["U"]
        axes[1].plot(u["step"], u["train"], label="train")
        axes[1].plot(u["step"], u["val"], label="held-out")
        axes[1].axhline(u["identity_val"], ls="--", c="grey", label="no repair")
        axes[1].set(title="U (HF L1)" if u.get("beats_identity", True) else "U (HF L1): left out", xlabel="step")
        axes[1].legend()
    else:
        axes[1].axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_finetune(ws: Workspace, cfg: FinetuneConfig, device: torch.device, seed: int, force: bool = False) -> bool:
    return ws.run_stage("finetune", cfg, {"seed": seed}, force, lambda run: finetune(run, ws, cfg, device, seed))


def finetune(run: StageRun, ws: Workspace, cfg: FinetuneConfig, device: torch.device, seed: int) -> str:
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    if cfg.levels < 1:
        raise InputError(f"levels must be >= 1, got {cfg.levels}")
    clean, bad, pairs = load_pairs(ws.stage_dir("mask_data"), cfg.domain, cfg.levels)
    train_ids, held = split_holdout(clean.shape[0], cfg.holdout, gen)
    record = train_and_save(run, ws, cfg, clean, bad, train_ids, held, device, gen)
    run.record.update(record)
    held_txt = (f"; held-out L1 {record['heldout']['l1_before']:.4f} -> {record['heldout']['l1_after']:.4f}"
                if "heldout" in record else "")
    u_txt = ""
    if "u_seconds" in record:
        kept = "kept" if record["u_used"] else "left out: no better than no HF repair on held-out crops"
        u_txt = f"; U {record['u_seconds']:.0f} s, stopped at {record['u_stopped_at']}, {kept}"
    return f"finetune: D {record['d_seconds']:.0f} s{held_txt}{u_txt}"


def train_lora(run: StageRun, cfg: FinetuneConfig, clean, bad, device, gen) -> dict[str, Any]:
    """SD 1.5 + ControlNet-tile with LoRA on the pairs shown as images in [0, 1] (LL / 2 for J = 1)."""
    from ..models import controlnet_lora as cl

    if not cfg.sd_model or not cfg.controlnet:
        raise InputError("--diffusion controlnet needs --sd-model PATH and --controlnet PATH (local folders)")
    pipe = cl.load_pipeline(Path(cfg.sd_model), Path(cfg.controlnet), device)
    params = cl.add_lora(pipe, cfg.lora_rank)
    opt = torch.optim.AdamW(params, lr=cfg.lora_lr)
    size = max(8, min(cfg.lora_crop, clean.shape[-1], clean.shape[-2]) // 8 * 8)
    losses = []
    with progress_bar("finetune D (LoRA)", cfg.lora_steps) as prog:
        for step in range(1, cfg.lora_steps + 1):
            idx = torch.randint(clean.shape[0], (1,), generator=gen)
            c, b = random_crops([clean, bad], idx, size, gen)
            losses.append(cl.lora_step(pipe, params, opt, ((c + 1) / 2).to(device), ((b + 1) / 2).to(device), gen))
            prog.update(0, completed=step, status=f"loss {losses[-1]:.4f}")
    cl.save_lora(run.dir / "D_lora", pipe, {"sd_model": str(Path(cfg.sd_model).resolve()),
                                            "controlnet": str(Path(cfg.controlnet).resolve()),
                                            "rank": cfg.lora_rank, "domain": cfg.domain, "levels": cfg.levels})
    return {"lora_final_loss": losses[-1] if losses else None, "lora_steps": cfg.lora_steps}


def train_and_save(run: StageRun, ws: Workspace, cfg: FinetuneConfig, clean, bad, train_ids, held,
                   device: torch.device, gen: torch.Generator) -> dict[str, Any]:
    t0 = time.perf_counter()
    if cfg.diffusion == "controlnet":
        record: dict[str, Any] = {"domain": cfg.domain, "levels": cfg.levels, "diffusion": "controlnet",
                                  **train_lora(run, cfg, clean[train_ids], bad[train_ids], device, gen),
                                  "d_seconds": round(time.perf_counter() - t0, 2), "num_pairs": int(clean.shape[0])}
        curves: dict[str, Any] = {}
        return finish_with_u(run, ws, cfg, record, curves, device, gen)
    ids = held if len(held) else train_ids
    prior = prior_folder(cfg)
    if prior is not None:
        d_model, d_extra, d_curve = finetune_prior_d(cfg, prior, clean[train_ids], bad[train_ids], clean[ids],
                                                     bad[ids], device, gen)
    else:
        d_model, d_curve = train_denoiser(cfg, clean[train_ids], bad[train_ids], device, gen, run.checkpointer("d"))
        d_extra = {"domain": cfg.domain, "levels": cfg.levels, "train_timesteps": cfg.train_timesteps}
    d_seconds = time.perf_counter() - t0
    save_model(run.dir / "D", d_model, d_extra)
    record: dict[str, Any] = {"domain": cfg.domain, "levels": cfg.levels, "d_seconds": round(d_seconds, 2),
                              "d_final_loss": d_curve["loss"][-1] if d_curve["loss"] else None,
                              "num_pairs": int(clean.shape[0]), "prior": None if prior is None else str(prior),
                              "heldout": heldout_check(cfg, d_model, d_extra, clean[ids], bad[ids], device)}
    if prior is not None:
        record["d_stopped_at"] = d_curve["stopped_at"]
    curves: dict[str, Any] = {"D": d_curve}
    return finish_with_u(run, ws, cfg, record, curves, device, gen, prior)


def finish_with_u(run: StageRun, ws: Workspace, cfg: FinetuneConfig, record: dict[str, Any], curves: dict[str, Any],
                  device: torch.device, gen: torch.Generator, prior: Path | None = None) -> dict[str, Any]:
    if cfg.domain == "wavelet" and cfg.use_u:
        t1 = time.perf_counter()
        renders, refs, _ = load_hf_data(ws)
        init = load_model(prior / "U", device)[0] if prior is not None else None
        u_model, u_curve = train_hf_unet(cfg, renders, refs, device, gen, run.checkpointer("u"), init)
        record.update({"u_seconds": round(time.perf_counter() - t1, 2), "u_best_val": u_curve["best_val"],
                       "u_identity_val": u_curve["identity_val"], "u_stopped_at": u_curve["stopped_at"],
                       "u_used": u_curve["beats_identity"]})
        if u_curve["beats_identity"]:  # else the repair leaves HF as rendered: what this scene needs
            save_model(run.dir / "U", u_model)
        curves["U"] = u_curve
    atomic_write_json(run.path("curves.json"), curves)
    if "D" in curves:
        plot_curves(run.path("curves.png"), curves)
    return record
