"""The 3DGS training loop shared by the coarse, mask-data and fine stages.

Adam per parameter group with 3DGS learning rates (means scaled by the scene extent, exponentially
decayed), L = 0.8·L1 + 0.2·(1 - SSIM) (+ a small alpha-vs-mask term when masks exist), random
backgrounds when masks exist, SH degree raised on a schedule, densification and floater removal.
A view whose image does not show the object's colours (`Frame.shows_colour`) teaches where the
object is not: L = outline_weight · mean(alpha outside its mask grown by outline_margin_px). It
never asks for matter, so where it and the photos disagree (a mirror plane a little off, an object
a little asymmetric) the photos decide. The first `half_size_until` of the schedule sees every view
at half size (`scene.dataset.halved`): those iterations fit the coarse shape at about half the cost
of a full-size one (docs/speed.md).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch.profiler import record_function

from ..errors import WgsError
from ..fields import option
from ..masking import grow
from ..metrics import ssim_map_fast
from ..progress import BAR, progress_bar
from ..resume import Checkpointer, check_interrupt, deferred_stop
from ..scene.dataset import Frame, halved
from ..threads import adapt as adapt_threads
from .callbacks import LoopState, Probe, ProbePoints, TimeBox, TrainingClock
from .init import floater_mask
from .pose_refine import CameraCorrections
from .render import rasterize
from .splats import Splats, activate
from .strategy import DensifyParams, DensifyStrategy, remove


@dataclass
class TrainConfig(DensifyParams):
    """The loop's settings (the coarse, mask-data and fine stages' configs extend them in
    `stages/<name>/settings.py`); densification fields and defaults come from `strategy.DensifyParams`."""

    iterations: int = option(2000, "Training iterations.")
    # the loop ends at this iteration (None: at `iterations`); the schedules (learning rate,
    # densification, half size, SH degree) still span `iterations`: a run stopped where it stopped gaining
    end_iteration: int | None = None
    max_seconds: float | None = option(None, "Stop training after this many seconds.")
    sh_degree: int = option(2, "Spherical-harmonics degree.", bounds=(0, 3))
    sh_increase_every: int = 500
    lr_means: float = 1.6e-4  # times the scene extent
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    ssim_weight: float = 0.2
    mask_weight: float = 0.1
    # views that teach the outline only (mirror views): the weight of the opacity outside their mask
    # grown by this many pixels (the photos decide within that margin)
    outline_weight: float = 1.0
    outline_margin_px: int = option(1, bounds=(0, None))
    # the views at half size (2x2 pixel means) for this fraction of the schedule: the early
    # iterations, which fit the coarse shape, cost about half as much
    half_size_until: float = option(0.0, bounds=(0.0, 1.0))
    random_background: bool = True
    init_points: int = 5000  # visual-hull points at most
    hull_resolution: int = 96
    floater_every: int = 500
    floater_k: int = 8
    floater_lambda: float = 3.0
    log_every: int = 50


# (frame index, iteration) -> per-pixel supervision weight [H, W] in [0, 1], or None for all pixels
PixelWeights = Callable[[int, int], torch.Tensor | None]


@dataclass
class PseudoViews:
    """Pseudo references for the fine stage: frames (with images), per-view weights (GaussianObject's
    distance weight), a schedule weight(it), and the background they were rendered on."""

    frames: list[Frame]
    weights: list[float]
    schedule: Callable[[int], float]
    background: torch.Tensor
    every: int = 2
    lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
    lpips_weight: float = 0.0

    def due(self, it: int, sched: int) -> bool:
        """Whether iteration `it` (at schedule position `sched`) trains on a pseudo view too."""
        return it % self.every == 0 and self.schedule(sched) > 0


@dataclass
class TrainResult:
    splats: Splats
    iterations: int
    seconds: float
    losses: list[float] = field(default_factory=list)
    curve: list[dict[str, float]] = field(default_factory=list)  # probe points: seconds, iteration, metrics
    probe_seconds: float = 0.0
    # the loop's state at its end with the Adam moments (`LoopState.snapshot`), where asked for
    # (`keep_state`): another loop can carry on from it (`train_gaussians(start=...)`)
    state: dict[str, Any] | None = None


class TrainingViews:
    """The training frames as the loop reads them, on the device: images, masks (None without),
    where each outline-only view allows matter (None for a view with colours), and cameras."""

    def __init__(self, frames: list[Frame], device: torch.device, has_masks: bool, outline_margin_px: int):
        self.images = [f.pixels.to(device) for f in frames]
        self.masks = [f.mask.to(device) if (has_masks and f.mask is not None) else None for f in frames]
        self.room = [
            grow(m, outline_margin_px) if (m is not None and not f.shows_colour) else None
            for f, m in zip(frames, self.masks, strict=True)
        ]
        self.cameras = [(f.viewmat.to(device), f.K.to(device), f.width, f.height) for f in frames]


def make_optimizers(params: Splats, cfg: TrainConfig, extent: float) -> dict[str, torch.optim.Optimizer]:
    """One Adam per parameter group, on the fused kernel (one pass over a group's tensors instead of
    a chain of element-wise ops: 2.0 ms instead of 4.5 ms for six groups of 15k Gaussians on one core)."""
    lrs = {
        "means": cfg.lr_means * extent,
        "quats": cfg.lr_quats,
        "scales": cfg.lr_scales,
        "opacities": cfg.lr_opacities,
        "sh0": cfg.lr_sh0,
        "shN": cfg.lr_shN,
    }
    return {
        k: torch.optim.Adam([{"params": [params[k]], "lr": lr, "name": k}], eps=1e-15, fused=True)
        for k, lr in lrs.items()
    }


def strategy_from(cfg: TrainConfig, extent: float) -> DensifyStrategy:
    """The strategy's thresholds are the config's (inherited) fields of the same names."""
    return DensifyStrategy(
        **{f.name: getattr(cfg, f.name) for f in dataclasses.fields(DensifyParams)}, scene_extent=extent
    )


def photometric_loss(
    render: torch.Tensor, target: torch.Tensor, ssim_weight: float, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """0.8·L1 + 0.2·(1 - SSIM) on [H, W, 3] images, optionally weighted per pixel by [H, W]."""
    l1 = (render - target).abs().mean(-1)
    ssim = ssim_map_fast(render.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], padding="reflect", eps=1e-12)
    return weighted_mean((1 - ssim_weight) * l1 + ssim_weight * (1 - ssim[0].mean(0)), weight)


def weighted_mean(err: torch.Tensor, pixel_weight: torch.Tensor | None) -> torch.Tensor:
    """Mean of [H, W], optionally weighted per pixel by [H, W]."""
    return err.mean() if pixel_weight is None else (err * pixel_weight).sum() / pixel_weight.sum().clamp_min(1.0)


def train_gaussians(
    splats: Splats,
    frames: list[Frame],
    cfg: TrainConfig,
    device: torch.device,
    *,
    extent: float,
    desc: str = "train",
    seed: int = 0,
    pixel_weights: PixelWeights | None = None,
    has_masks: bool = True,
    on_step: Callable[[int, Splats], None] | None = None,
    pseudo: PseudoViews | None = None,
    checkpoint: Checkpointer | None = None,
    probe: Probe | None = None,
    cameras: CameraCorrections | None = None,
    start: dict[str, Any] | None = None,
    keep_state: bool = False,
) -> TrainResult:
    """Optimise `splats` (raw, normalised world) on `frames` (with images). Returns the new splats.

    pixel_weights(i, it) -> [H, W] supervision weights for frame i (None: all pixels count);
    on_step(it, params) is called after every iteration with the current (detached) parameters.
    pseudo: extra views trained with L1 + L2 (+ LPIPS) every `pseudo.every` iterations.
    checkpoint: saves the full state periodically, at the end and on Ctrl-C; continues from it on --resume.
    probe: measured at the start, every `probe.every_s` training seconds and at the end (TrainResult.curve).
    cameras: corrections of the frames' cameras, trained with the model (`pose_refine`).
    start: another loop's state (`TrainResult.state`) to carry on from, on these frames: its
    parameters, moments, densification state, generators and schedule position (a checkpoint to
    resume from comes first); `splats` is then not used.
    keep_state: TrainResult.state holds the state at the end.
    """
    params = {k: v.detach().to(device).clone().requires_grad_(True) for k, v in splats.items()}
    strategy = strategy_from(cfg, extent)
    clock = TrainingClock()
    loop = LoopState(
        params,
        make_optimizers(params, cfg, extent),
        strategy.initial_state(),
        torch.Generator().manual_seed(seed),
        clock,
        ProbePoints(probe, clock),
        cameras,
    )
    gen = loop.generator
    sizes = [TrainingViews(frames, device, has_masks, cfg.outline_margin_px)]  # full size, then half
    pseudo_sizes = [pseudo.frames if pseudo is not None else []]
    if cfg.half_size_until > 0:
        sizes.append(TrainingViews([halved(f) for f in frames], device, has_masks, cfg.outline_margin_px))
        pseudo_sizes.append([halved(f) for f in pseudo_sizes[0]])
    max_deg = int(math.isqrt(1 + params["shN"].shape[1])) - 1
    decay = (cfg.lr_means_final / cfg.lr_means) ** (1.0 / max(cfg.iterations, 1))
    time_box = TimeBox(cfg.iterations, cfg.max_seconds)
    saved = checkpoint.load() if checkpoint is not None else None
    if saved is None and start is not None:
        saved = carried_over(start)
    if saved is not None:
        loop.restore(saved, device, lambda restored: make_optimizers(restored, cfg, extent))
    params, optimizers, state = loop.params, loop.optimizers, loop.strategy
    losses, order = loop.losses, loop.order

    last = min(cfg.end_iteration or cfg.iterations, cfg.iterations)
    it = loop.it
    with progress_bar(desc, last) as prog, deferred_stop():
        prog.update(BAR, completed=it)
        loop.probes.at_start(params, it)
        for it in range(it + 1, (it if loop.finished else last) + 1):  # noqa: B020 - resumes the count
            adapt_threads()
            prev_sched = loop.sched
            sched = loop.sched = time_box.schedule(it, clock)
            loop.it = it
            if not order:
                order.extend(torch.randperm(len(frames), generator=gen).tolist())
            i = order.pop()
            half = sched <= cfg.half_size_until * cfg.iterations and len(sizes) > 1
            views = sizes[int(half)]
            image, mask, room = views.images[i], views.masks[i], views.room[i]
            viewmat, K, w, h = views.cameras[i]
            if mask is not None and cfg.random_background:
                bg = torch.rand(3, generator=gen).to(device)
            else:
                bg = torch.ones(3, device=device) if mask is not None else torch.zeros(3, device=device)
            target = image if mask is None else image * mask[..., None] + bg * (1 - mask[..., None])
            deg = min(max_deg, (sched - 1) // max(cfg.sh_increase_every, 1))
            with record_function("wgs:render"):
                means, quats, scales, opac, sh = activate(params)
                if cameras is not None:
                    means, quats = cameras.move(i, means, quats, viewmat)
                rgb, alpha, meta = rasterize(means, quats, scales, opac, sh[:, : (deg + 1) ** 2], viewmat, K, w, h, bg)
            with record_function("wgs:loss"):
                if room is not None:  # no colours (and so nothing for pixel weights to hide): only the outline
                    loss = cfg.outline_weight * (alpha[..., 0] * (1 - room)).mean()
                else:
                    weight = pixel_weights(i, it) if pixel_weights is not None else None
                    if weight is not None and half:
                        weight = torch.nn.functional.avg_pool2d(weight[None, None], 2)[0, 0]
                    loss = photometric_loss(rgb, target, cfg.ssim_weight, weight)
                    if mask is not None and cfg.mask_weight > 0:
                        loss = loss + cfg.mask_weight * weighted_mean((alpha[..., 0] - mask).abs(), weight)
            if pseudo is not None and pseudo.due(it, sched):
                with record_function("wgs:pseudo_view"):
                    loss = loss + pseudo_loss(params, pseudo, pseudo_sizes[int(half)], it, sched, deg, device, cfg)
            with record_function("wgs:backward"):
                loss.backward()
            if not torch.isfinite(loss):
                raise WgsError(f"{desc}: loss became non-finite at iteration {it}; nothing was saved")
            with record_function("wgs:adam"):
                for name, opt in optimizers.items():
                    if name == "means":
                        opt.param_groups[0]["lr"] = cfg.lr_means * extent * decay ** min(sched, cfg.iterations)
                    opt.step()
                    opt.zero_grad(set_to_none=True)
                if cameras is not None:
                    cameras.step()
            with record_function("wgs:finite_check"):
                # a group's sum is non-finite when an element is (or on overflow): the exact test only then
                if not torch.isfinite(torch.stack([p.detach().sum() for p in params.values()])).all():
                    bad = [k for k, p in params.items() if not torch.isfinite(p).all()]
                    if bad:
                        raise WgsError(
                            f"{desc}: parameter group(s) {', '.join(bad)} became non-finite at iteration "
                            f"{it}; nothing was saved"
                        )
            with torch.no_grad(), record_function("wgs:densify"):
                strategy.accumulate(state, meta)
                strategy.step(params, optimizers, state, sched, prev_sched)
                if (
                    cfg.floater_every > 0
                    and prev_sched // cfg.floater_every < sched // cfg.floater_every
                    and sched < cfg.refine_stop
                    and params["means"].shape[0] > 100
                ):
                    drop = floater_mask(params["means"], cfg.floater_k, cfg.floater_lambda)
                    if drop.any():
                        remove(params, optimizers, drop)
            losses.append(loss.item())
            if on_step is not None:
                on_step(it, {k: v.detach() for k, v in params.items()})
            if it % cfg.log_every == 0 or it == last:
                rate = it / max(clock.seconds(), 1e-9)
                recent = losses[-cfg.log_every :]
                prog.update(
                    BAR,
                    completed=it,
                    status=f"loss {sum(recent) / len(recent):.4f}  "
                    f"{params['means'].shape[0]} gaussians  {rate:.1f} it/s",
                )
            loop.finished = loop.probes.after_step(params, it, it == last or time_box.over(clock))
            if checkpoint is not None and (loop.finished or checkpoint.due()):
                checkpoint.save(loop.snapshot())
            check_interrupt(desc, it, checkpoint, loop.snapshot)
            if loop.finished:
                break
    out = {k: v.detach() for k, v in params.items()}
    kept = loop.snapshot(moments=True) if keep_state else None
    return TrainResult(out, it, clock.seconds(), losses, loop.probes.curve, loop.probes.seconds, kept)


def carried_over(state: dict[str, Any]) -> dict[str, Any]:
    """Another loop's state as a new loop starts from it: its parameters, moments, densification
    state, generators and iteration; its own views' order, losses, clock and probe points left behind."""
    return {**state, "order": [], "losses": [], "elapsed": 0.0, "curve": [], "probe_s": 0.0, "finished": False}


def pseudo_loss(
    params: Splats,
    pseudo: PseudoViews,
    frames: list[Frame],
    it: int,
    sched: int,
    deg: int,
    device: torch.device,
    cfg: TrainConfig,
) -> torch.Tensor:
    """L1 + L2 (+ LPIPS) against one pseudo reference (`frames`: pseudo.frames at the size this
    iteration trains at). Where the frame has a mask (0 where the silhouette model is sure of
    background, 1 where the object may be), the reference shows the background outside it and
    opacity is pushed to 0 there: pseudo views then carve too. Inside it opacity is left free, and
    the background stays the reference's own (a random one would turn the reference's background
    pixels near the object into white halos)."""
    j = (it // pseudo.every) % len(frames)
    f = frames[j]
    bg, target = pseudo.background.to(device), f.pixels.to(device)
    if f.mask is not None:
        a = f.mask.to(device)[..., None]
        target = target * a + bg * (1 - a)
    means, quats, scales, opac, sh = activate(params)
    rgb, alpha, _ = rasterize(
        means, quats, scales, opac, sh[:, : (deg + 1) ** 2], f.viewmat.to(device), f.K.to(device), f.width, f.height, bg
    )
    diff = rgb - target
    loss = diff.abs().mean() + diff.pow(2).mean()
    if f.mask is not None and cfg.mask_weight > 0:
        loss = loss + cfg.mask_weight * (alpha[..., 0] * (1 - f.mask.to(device))).mean()
    if pseudo.lpips is not None and pseudo.lpips_weight > 0:
        perceptual = pseudo.lpips(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]).mean()
        loss = loss + pseudo.lpips_weight * perceptual
    return pseudo.schedule(sched) * pseudo.weights[j] * loss


@torch.no_grad()
def render_frame(
    splats: Splats, frame: Frame, device: torch.device, background: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render a frame's camera: rgb [H, W, 3], alpha [H, W, 1] (CPU tensors)."""
    means, quats, scales, opac, sh = activate({k: v.to(device) for k, v in splats.items()})
    rgb, alpha, _ = rasterize(
        means,
        quats,
        scales,
        opac,
        sh,
        frame.viewmat.to(device),
        frame.K.to(device),
        frame.width,
        frame.height,
        background.to(device),
    )
    return rgb.clamp(0, 1).cpu(), alpha.cpu()
