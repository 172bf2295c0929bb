"""Gaussian parameters as a dict of raw tensors (gsplat's layout), activations, checkpoints, PLY.

Raw keys: means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (log), opacities [N] (logit),
sh0 [N, 1, 3], shN [N, K-1, 3]. Activations live only in `activate`.
Checkpoints and PLY files hold the scene's original world coordinates; training runs in the
normalised world (`Normalisation`), converted on load and save.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..io.checkpoint import UnreadableCheckpoint, read_checkpoint, write_checkpoint
from ..io.ply import read_ply, write_ply
from ..scene.convention import Normalisation
from .sh import num_sh_bases, rgb_to_sh0

Splats = dict[str, torch.Tensor]
KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
CHECKPOINT_VERSION = 1


def create_splats(
    points: torch.Tensor, colors: torch.Tensor, scales: torch.Tensor, sh_degree: int, opacity: float = 0.1
) -> Splats:
    """New splats at points [N, 3] with colours [N, 3] in [0, 1] and isotropic scales [N] (> 0)."""
    n = points.shape[0]
    k = num_sh_bases(sh_degree)
    dev, dt = points.device, points.dtype
    quats = torch.zeros(n, 4, device=dev, dtype=dt)
    quats[:, 0] = 1.0
    return {
        "means": points.clone(),
        "quats": quats,
        "scales": torch.log(scales.clamp_min(1e-8))[:, None].repeat(1, 3),
        "opacities": torch.full((n,), math.log(opacity / (1 - opacity)), device=dev, dtype=dt),
        "sh0": rgb_to_sh0(colors)[:, None, :].clone(),
        "shN": torch.zeros(n, k - 1, 3, device=dev, dtype=dt),
    }


def activate(splats: Splats) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> means [N,3], quats [N,4], scales [N,3] (exp), opacities [N] (sigmoid), sh [N,K,3]."""
    return (
        splats["means"],
        splats["quats"],
        torch.exp(splats["scales"]),
        torch.sigmoid(splats["opacities"]),
        torch.cat([splats["sh0"], splats["shN"]], dim=1),
    )


def sh_degree(splats: Splats) -> int:
    return int(math.isqrt(1 + splats["shN"].shape[1])) - 1


def to_world(splats: Splats, norm: Normalisation) -> Splats:
    """Normalised -> original world coordinates (translation + uniform scale; rotations unchanged)."""
    out = {k: v.detach().clone() for k, v in splats.items()}
    c = torch.as_tensor(norm.center, dtype=out["means"].dtype, device=out["means"].device)
    out["means"] = out["means"] * norm.scale + c
    out["scales"] = out["scales"] + math.log(norm.scale)
    return out


def from_world(splats: Splats, norm: Normalisation) -> Splats:
    out = {k: v.detach().clone() for k, v in splats.items()}
    c = torch.as_tensor(norm.center, dtype=out["means"].dtype, device=out["means"].device)
    out["means"] = (out["means"] - c) / norm.scale
    out["scales"] = out["scales"] - math.log(norm.scale)
    return out


# ----------------------------------------------------------------------------------- checkpoints
def save_checkpoint(
    path: Path, splats: Splats, norm: Normalisation, step: int, extra: dict[str, Any] | None = None
) -> None:
    """Atomic `{"step", "splats", "version", "normalisation", ...}` in world coordinates."""
    world = {k: v.detach().cpu().contiguous() for k, v in to_world(splats, norm).items()}
    write_checkpoint(
        path,
        {
            "version": CHECKPOINT_VERSION,
            "step": int(step),
            "splats": world,
            "normalisation": norm.to_json(),
            **(extra or {}),
        },
    )


def load_checkpoint(
    path: Path, norm: Normalisation | None = None, device: torch.device | str = "cpu"
) -> tuple[Splats, dict[str, Any]]:
    """Load (weights_only: no pickle code runs) and validate; returns normalised splats if `norm`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint not found", path)
    try:
        blob = read_checkpoint(path)
    except UnreadableCheckpoint as exc:  # truncated zip, pickle payload refused by weights_only, ...
        raise InputError(f"not a valid wgs checkpoint ({exc})", path) from None
    if not isinstance(blob, dict) or not isinstance(blob.get("splats"), dict):
        raise InputError("not a wgs checkpoint (no 'splats' table)", path)
    if blob.get("version") != CHECKPOINT_VERSION:
        raise InputError(f"checkpoint version {blob.get('version')!r}, this wgs reads {CHECKPOINT_VERSION}", path)
    sp = blob["splats"]
    missing = [k for k in KEYS if k not in sp]
    if missing:
        raise InputError(f"checkpoint lacks {', '.join(missing)}", path)
    n = sp["means"].shape[0]
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3)}
    for k, shp in shapes.items():
        if tuple(sp[k].shape) != shp:
            raise InputError(f"checkpoint tensor '{k}' has shape {tuple(sp[k].shape)}, expected {shp}", path)
    k_rest = sp["shN"].shape[1] if sp["shN"].dim() == 3 else -1
    if sp["shN"].dim() != 3 or sp["shN"].shape[0] != n or math.isqrt(k_rest + 1) ** 2 != k_rest + 1:
        raise InputError(f"checkpoint 'shN' has shape {tuple(sp['shN'].shape)}: not an SH degree", path)
    splats = {k: sp[k].to(device=device, dtype=torch.float32) for k in KEYS}
    if norm is not None:
        splats = from_world(splats, norm)
    return splats, blob


# ----------------------------------------------------------------------------------- PLY
VIEWER_SH_DEGREE = 3  # INRIA's SIBR viewer reads a fixed degree-3 record (45 f_rest): stages pad to it


def ply_attributes(sh_deg: int) -> list[str]:
    """The standard 3DGS attribute order (INRIA layout read by SuperSplat and gsplat's viewer)."""
    n_rest = 3 * (num_sh_bases(sh_deg) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def export_ply(path: Path, splats: Splats, pad_to_degree: int | None = None) -> int:
    """Write binary little-endian float32 3DGS PLY; rows with NaN/inf are dropped. Returns rows written."""
    sp = {k: v.detach().cpu().float() for k, v in splats.items()}
    n = sp["means"].shape[0]
    deg = sh_degree(sp)
    shN = sp["shN"]
    if pad_to_degree is not None and pad_to_degree > deg:
        shN = torch.cat([shN, torch.zeros(n, num_sh_bases(pad_to_degree) - 1 - shN.shape[1], 3)], dim=1)
        deg = pad_to_degree
    cols = [
        sp["means"],
        torch.zeros(n, 3),
        sp["sh0"][:, 0, :],
        shN.transpose(1, 2).reshape(n, -1),  # channel-major: all R, then G, then B
        sp["opacities"][:, None],
        sp["scales"],
        sp["quats"],
    ]
    data = torch.cat(cols, dim=1).numpy().astype("<f4")
    data = data[np.isfinite(data).all(axis=1)]
    write_ply(path, ply_attributes(deg), data)
    return len(data)


SPLAT_ROW = 32  # bytes per Gaussian in antimatter15's .splat layout


def splat_bytes(splats: Splats, rotation: torch.Tensor | None = None, translation: torch.Tensor | None = None) -> bytes:
    """antimatter15's `.splat` layout (WebGL viewers read it): per Gaussian, position float32 x3,
    scale float32 x3 (activated), colour RGBA uint8 (SH degree 0, opacity), rotation uint8 x4
    (w, x, y, z) * 128 + 128; largest and most opaque first. No view-dependent colour.
    `rotation` [3, 3] and `translation` [3] move the model first (x -> R x + t).
    """
    from .project import matrix_to_quat, quat_multiply
    from .sh import C0

    sp = {k: v.detach().cpu().double() for k, v in splats.items()}
    means, quats = sp["means"], torch.nn.functional.normalize(sp["quats"], dim=-1)
    if rotation is not None:
        R = rotation.double()
        means = means @ R.T
        quats = quat_multiply(matrix_to_quat(R)[None], quats)
    if translation is not None:
        means = means + translation.double()
    scales = sp["scales"].exp()
    alpha = torch.sigmoid(sp["opacities"])
    rgb = (0.5 + C0 * sp["sh0"][:, 0, :]).clamp(0, 1)
    ok = torch.isfinite(torch.cat([means, scales, quats, rgb, alpha[:, None]], 1)).all(1)
    order = torch.argsort(-(scales.prod(1) * alpha)[ok])
    means, scales, quats, rgb, alpha = (t[ok][order] for t in (means, scales, quats, rgb, alpha))
    out = np.zeros(len(means), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    out["pos"], out["scale"] = means.numpy(), scales.numpy()
    out["rgba"] = (torch.cat([rgb, alpha[:, None]], 1) * 255).round().clamp(0, 255).numpy()
    out["rot"] = (quats * 128 + 128).round().clamp(0, 255).numpy()
    return out.tobytes()


def import_ply(path: Path) -> Splats:
    """Read a 3DGS PLY (binary little endian, float32 properties) into raw splats."""
    names, arr = read_ply(path)
    n = len(arr)
    col = {name: i for i, name in enumerate(names)}
    n_rest = sum(1 for x in names if x.startswith("f_rest_"))
    needed = ["x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"]
    if any(x not in col for x in needed) or n_rest % 3 or math.isqrt(n_rest // 3 + 1) ** 2 != n_rest // 3 + 1:
        raise InputError("not a 3DGS PLY (missing attributes or an SH count that is no degree)", Path(path))

    def take(keys: list[str]) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(arr[:, [col[k] for k in keys]]))

    k1 = n_rest // 3
    return {
        "means": take(["x", "y", "z"]),
        "quats": take([f"rot_{i}" for i in range(4)]),
        "scales": take([f"scale_{i}" for i in range(3)]),
        "opacities": take(["opacity"])[:, 0].contiguous(),
        "sh0": take([f"f_dc_{i}" for i in range(3)])[:, None, :].contiguous(),
        "shN": take([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k1).transpose(1, 2).contiguous(),
    }
