"""The repair of a render by the fine-tuned models: D on the LL subband (or RGB), U on the HF
subbands, inverse DWT. Shared by `wgs repair` (pseudo references) and `wgs eval` (repair gain)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ..wavelet.haar import dwt2, idwt2, split_highs, stack_highs
from .data import from_model, to_model
from .denoiser_meta import DenoiserMeta
from .sampling import sdedit_repair, single_step
from .scheduler import DDIMScheduler
from .storage import load_model


def chw_to_hwc(x: torch.Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).float().numpy()


RepairFn = Callable[[torch.Tensor], torch.Tensor]  # [B, 3, h, w] model space -> repaired, model space


class RepairSettings(Protocol):
    """What the repair reads of its stage's config (`stages/repair/settings.py`, `RepairConfig`)."""

    strength: float  # SDEdit: the noise level a render is taken to before denoising
    steps: int  # DDIM steps
    symmetries: int  # flips / transposes each render is repaired under, averaged


# the square's symmetries as (transpose, flip rows, flip columns)
SYMMETRIES = (
    (False, False, False),
    (False, False, True),
    (False, True, False),
    (True, False, False),
    (False, True, True),
    (True, False, True),
    (True, True, False),
    (True, True, True),
)


def _apply_symmetry(x: torch.Tensor, sym: tuple[bool, bool, bool], inverse: bool = False) -> torch.Tensor:
    transpose, rows, cols = sym
    dims = [d for d, on in ((-2, rows), (-1, cols)) if on]
    if not inverse and transpose:
        x = x.transpose(-2, -1)
    x = x.flip(dims) if dims else x
    return x.transpose(-2, -1) if inverse and transpose else x


def symmetrized(fn: RepairFn, n: int, first: int = 0) -> RepairFn:
    """fn averaged over n (1..8) symmetries of the square (flips, transposes) of its input, taken
    cyclically from SYMMETRIES[first].

    A small D is not equivariant to them, so its errors differ between them while the object does
    not; an ensemble gives each member its own (`first`), which costs nothing."""
    if not 1 <= n <= len(SYMMETRIES):
        raise ValueError(f"symmetries must be 1..{len(SYMMETRIES)}, got {n}")
    syms = [SYMMETRIES[(first + i) % len(SYMMETRIES)] for i in range(n)]
    if syms == [SYMMETRIES[0]]:
        return fn

    def averaged(x: torch.Tensor) -> torch.Tensor:
        outs = [_apply_symmetry(fn(_apply_symmetry(x, s)), s, inverse=True) for s in syms]
        return torch.stack(outs).mean(0)

    return averaged


@dataclass(frozen=True)
class Repairer:
    """What repairs a render: D's function (model space), U (or None), D's metadata, and under how
    many of the square's symmetries each render is repaired (RepairConfig.symmetries)."""

    fn: RepairFn
    U: torch.nn.Module | None
    meta: DenoiserMeta
    symmetries: int = 1


def embedded_repairer(
    D: torch.nn.Module, cfg: RepairSettings, meta: DenoiserMeta, gen: torch.Generator, device: torch.device
) -> RepairFn:
    """SDEdit for a D trained by denoising; one step from the render for a prior-trained D."""
    sched = DDIMScheduler(meta.train_timesteps)
    if meta.start == "corrupted":
        return lambda x: single_step(D, sched, x.to(device), meta.repair_t, gen).cpu()
    return lambda x: sdedit_repair(D, sched, x.to(device), cfg.strength, cfg.steps, gen).cpu()


def controlnet_repairer(pipe, cfg: RepairSettings, seed: int) -> RepairFn:
    """SD img2img + ControlNet on images in [0, 1], padded to a multiple of 8 and cropped back."""
    from ..models import controlnet_lora as cl
    from ..models.blocks import pad_to_multiple

    def fn(x: torch.Tensor) -> torch.Tensor:
        img, (h, w) = pad_to_multiple(((x + 1) / 2).clamp(0, 1), 8)
        out = cl.repair(pipe, img.to(pipe.device), cfg.strength, cfg.steps, seed)
        return out[..., :h, :w] * 2 - 1

    return fn


@torch.no_grad()
def repair_image(
    render: torch.Tensor,
    repair_fn: RepairFn,
    U: torch.nn.Module | None,
    domain: str,
    device: torch.device,
    levels: int = 1,
) -> tuple[torch.Tensor, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """render [H, W, 3] -> pseudo reference [H, W, 3] and the corrupted / repaired subbands.

    wavelet: D repairs LL_J; the coarser HF levels are kept, LL_1 is rebuilt from them, and U
    repairs the finest HF level with LL_1 as context."""
    x = render.permute(2, 0, 1)[None].double()
    h, w = x.shape[-2:]
    if domain == "rgb":
        out = from_model(repair_fn(to_model(x.float(), "rgb")), "rgb").double()
        bands_in = {"RGB": chw_to_hwc(x)}
        bands_out = {"RGB": chw_to_hwc(out)}
    else:
        llJ, highs = dwt2(x, levels)
        llJ_fixed = from_model(repair_fn(to_model(llJ.float(), "wavelet", levels)), "wavelet", levels).double()
        size1 = (int(highs[0][0].shape[-2]), int(highs[0][0].shape[-1]))
        ll1 = idwt2(llJ, highs[1:], size=size1) if levels > 1 else llJ
        ll1_fixed = idwt2(llJ_fixed, highs[1:], size=size1) if levels > 1 else llJ_fixed
        hf = highs[0]
        hf_fixed = hf
        if U is not None:
            hf_fixed = split_highs(U(stack_highs(hf).float().to(device), ll1.float().to(device)).cpu().double())
        out = idwt2(ll1_fixed, [hf_fixed], size=(int(h), int(w)))
        names = ("LL", "LH", "HL", "HH")
        bands_in = dict(zip(names, map(chw_to_hwc, (ll1, *hf)), strict=True))
        bands_out = dict(zip(names, map(chw_to_hwc, (ll1_fixed, *hf_fixed)), strict=True))
    return out[0].permute(1, 2, 0).clamp(0, 1).float(), bands_in, bands_out


def load_repairer(folder: Path, cfg: RepairSettings, device: torch.device, seed: int) -> Repairer:
    """D's repair function, U (or None) and D's config from a finetune folder (D/ or D_lora/, U/)."""
    gen = torch.Generator().manual_seed(seed)
    if (folder / "D_lora").is_dir():
        from .controlnet_lora import load_lora

        pipe, d_cfg = load_lora(folder / "D_lora", device)
        meta = DenoiserMeta.from_config(d_cfg, folder / "D_lora")
        repair_fn = controlnet_repairer(pipe, cfg, seed)
    else:
        D, d_cfg = load_model(folder / "D", device)
        meta = DenoiserMeta.from_config(d_cfg, folder / "D" / "config.json")
        repair_fn = embedded_repairer(D, cfg, meta, gen, device)
    u_dir = folder / "U"
    U = load_model(u_dir, device)[0] if (meta.domain == "wavelet" and u_dir.is_dir()) else None
    return Repairer(repair_fn, U, meta, cfg.symmetries)
