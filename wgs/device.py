"""Device selection: `auto` prefers cuda, then mps, then cpu."""

from __future__ import annotations

import torch

from .errors import WgsError


def resolve_device(spec: str = "auto") -> torch.device:
    """Turn `auto|cpu|cuda[:N]|mps` into a torch.device that exists on this machine."""
    spec = (spec or "auto").strip().lower()
    if spec == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(spec)
    except RuntimeError as exc:
        raise WgsError(f"unknown device {spec!r} (use auto, cpu, cuda[:N] or mps)") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise WgsError(f"device {spec!r} requested but CUDA is not available")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise WgsError(f"device {spec!r}: only {torch.cuda.device_count()} CUDA device(s)")
    if dev.type == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise WgsError("device 'mps' requested but MPS is not available")
    return dev
