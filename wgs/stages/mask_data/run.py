"""Stage 2: corrupted/clean training pairs for the repair models.

Strategies: `orm` (online random masking, the default: ONE model G_d whose references are partly
hidden under drifting random masks), `offline-rm` (the same masks, not drifting) and `loo`
(GaussianObject's leave-one-out: N models, each without one view). At regular intervals after a
warm-up the models are rendered at the training views; each (render, reference) pair is stored
as Haar subbands (LL pairs for D) and as RGB (for the RGB-domain ablation). HF pairs for U are
the coarse stage's subbands of its renders and references, listed in the index.
"""

from __future__ import annotations

import time
from typing import Any

import torch

from ...errors import InputError
from ...gaussians.splats import Splats
from ...gaussians.trainer import render_frame, train_gaussians
from ...io import atomic_write_json, read_json
from ...io.exr import write_subbands
from ...masking import make_region_masks
from ...scene.dataset import PreparedScene, composite, load_prepared
from ...workspace import StageRun, Workspace
from ..shared import background_for, initial_splats, subband_file, subbands_hwc
from ..stage import StageEnv
from .settings import MaskDataConfig


class PairWriter:
    """Renders models at training views and writes (corrupted, clean) pairs."""

    def __init__(self, run: StageRun, scene: PreparedScene, device: torch.device, strategy: str):
        self.run, self.scene, self.device, self.strategy = run, scene, device, strategy
        self.bg = background_for(scene)
        self.refs = [composite(f.pixels, f.mask, self.bg) for f in scene.train]
        self.ref_bands = [subbands_hwc(r) for r in self.refs]
        # (model, iteration, view) -> entry, in write order; persisted so a resumed run keeps earlier pairs
        self.entries_file = run.path("pairs", "entries.json")
        self.entries: dict[str, dict[str, Any]] = {}
        if self.entries_file.exists():
            self.entries = {e["key"]: e for e in read_json(self.entries_file)}

    @property
    def pairs(self) -> list[dict[str, Any]]:
        return [{"id": i, **{k: v for k, v in e.items() if k != "key"}} for i, e in enumerate(self.entries.values())]

    def write(self, splats: Splats, view: int, it: int, hidden: torch.Tensor | None, model: str) -> None:
        f = self.scene.train[view]
        render, _ = render_frame(splats, f, self.device, self.bg)
        stem = f"{f.name.rsplit('.', 1)[0]}_{model}_{it:06d}"
        hid = torch.zeros(f.height, f.width) if hidden is None else hidden
        # hidden area at LL resolution: the fraction of each 2x2 block that was hidden
        hid_ll = subbands_hwc(hid[..., None].repeat(1, 1, 3))["LL"][..., :1] / 2.0
        ll_file = f"pairs/ll/{stem}.exr"
        write_subbands(
            self.run.path(ll_file), {"LL": self.ref_bands[view]["LL"], "cLL": subbands_hwc(render)["LL"], "M": hid_ll}
        )
        rgb_file = f"pairs/rgb/{stem}.exr"
        write_subbands(
            self.run.path(rgb_file),
            {"RGB": self.refs[view].numpy(), "cRGB": render.numpy(), "M": hid[..., None].numpy()},
        )
        key = f"{model}/{it}/{view}"
        self.entries[key] = {
            "key": key,
            "view": f.name,
            "iteration": it,
            "model": model,
            "ll": ll_file,
            "rgb": rgb_file,
        }
        atomic_write_json(self.entries_file, list(self.entries.values()))


def run_orm(
    cfg: MaskDataConfig, scene: PreparedScene, device: torch.device, seed: int, writer: PairWriter
) -> dict[str, Any]:
    objects = torch.stack([f.mask if f.mask is not None else torch.ones(f.height, f.width) for f in scene.train])
    regions = make_region_masks(
        objects,
        cfg.n_regions,
        cfg.coverage,
        cfg.drift,
        cfg.drift_period,
        offline=cfg.strategy == "offline-rm",
        seed=seed,
    )

    def weights(i: int, it: int) -> torch.Tensor:
        return (1.0 - regions.hidden(i, it)).to(device)

    def snapshot(it: int, params: Splats) -> None:
        if it >= cfg.warmup and it % cfg.pair_every == 0:
            for v, f in enumerate(scene.train):
                if f.shows_colour:
                    writer.write(params, v, it, regions.hidden(v, it), "gd")

    res = train_gaussians(
        initial_splats(scene, cfg, seed),
        scene.train,
        cfg,
        device,
        extent=1.0,
        desc=f"mask-data {cfg.strategy}",
        seed=seed,
        pixel_weights=weights,
        has_masks=scene.has_masks,
        on_step=snapshot,
        checkpoint=writer.run.checkpointer("gd"),
    )
    return {"models": 1, "iterations": res.iterations}


def run_loo(
    cfg: MaskDataConfig, scene: PreparedScene, device: torch.device, seed: int, writer: PairWriter
) -> dict[str, Any]:
    left_outs = [i for i, f in enumerate(scene.train) if f.shows_colour]  # outline-only views make no pairs
    for k, left_out in enumerate(left_outs):
        keep = [f for i, f in enumerate(scene.train) if i != left_out]
        sub = PreparedScene(scene.info, scene.norm, keep, [])

        def snapshot(it: int, params: Splats, v: int = left_out) -> None:
            if it >= cfg.warmup and it % cfg.pair_every == 0:
                writer.write(params, v, it, None, f"loo{v}")

        train_gaussians(
            initial_splats(sub, cfg, seed),
            keep,
            cfg,
            device,
            extent=1.0,
            desc=f"mask-data loo {k + 1}/{len(left_outs)}",
            seed=seed,
            has_masks=scene.has_masks,
            on_step=snapshot,
            checkpoint=writer.run.checkpointer(f"loo{left_out}"),
        )
    return {"models": len(left_outs), "iterations": cfg.iterations * len(left_outs)}


def hf_views(ws: Workspace, scene: PreparedScene) -> list[str]:
    """The training views whose coarse render and reference subbands (coarse's `subbands`) train U."""
    for f in scene.colour_views:
        for kind in ("render", "ref"):
            if not (p := subband_file(ws, kind, f.name)).is_file():
                raise InputError("coarse subband file missing: rerun `wgs coarse --force`", p)
    return [f.name for f in scene.colour_views]


def run_mask_data(ws: Workspace, cfg: MaskDataConfig, env: StageEnv, force: bool = False) -> bool:
    return ws.run_staged(
        "mask_data", cfg, {"seed": env.seed}, force, lambda run: make_pairs(run, ws, cfg, env.device, env.seed)
    )


def make_pairs(run: StageRun, ws: Workspace, cfg: MaskDataConfig, device: torch.device, seed: int) -> str:
    scene = load_prepared(ws.output("prepare", "prepared"))
    torch.manual_seed(seed)
    writer = PairWriter(run, scene, device, cfg.strategy)
    t0 = time.perf_counter()
    stats = (run_loo if cfg.strategy == "loo" else run_orm)(cfg, scene, device, seed, writer)
    seconds = time.perf_counter() - t0
    atomic_write_json(
        run.output("index"), {"strategy": cfg.strategy, "pairs": writer.pairs, "hf_views": hf_views(ws, scene)}
    )
    run.record.update(
        {"strategy": cfg.strategy, "num_pairs": len(writer.pairs), "strategy_seconds": round(seconds, 2), **stats}
    )
    return f"mask-data: {cfg.strategy}, {len(writer.pairs)} pairs from {stats['models']} model(s) in {seconds:.1f} s"


# what tools and other packages may use; the rest is this stage's own
__all__ = ["run_mask_data"]
