"""What a saved D needs beside its weights (its config.json fields): the domain it repairs, how
it was trained and how the repair runs it.

Two objectives, named by where D's noised input starts:
- `clean`: plain denoising training, the clean crop noised to any level; the repair runs SDEdit
  from the noised render.
- `corrupted` (Difix-style single step): the *render* noised to a low level t < t_max, the target
  the ground truth; the repair runs D once at t = `repair_t` (0: deterministic).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from ..errors import InputError


@dataclass
class DenoiserMeta:
    """What a saved D needs beside its weights to be used: its domain, how it was trained and how
    the repair runs it (stored in its config.json)."""

    domain: str = "wavelet"  # wavelet (LL subband) | rgb
    levels: int = 1  # Haar levels of the LL subband
    train_timesteps: int = 1000
    start: str = "clean"  # clean | corrupted: see the module docstring
    t_max: int | None = None  # corrupted start: training noise levels 0 .. t_max - 1
    repair_t: int = 0  # corrupted start: the noise level the repair runs at
    prior: str | None = None  # the prior folder it was fine-tuned from

    @classmethod
    def from_config(cls, cfg: dict[str, Any], where: Path | None = None) -> DenoiserMeta:
        meta = cls(**{f.name: cfg[f.name] for f in fields(cls) if f.name in cfg})
        if meta.start not in ("clean", "corrupted") or (meta.start == "corrupted" and meta.t_max is None):
            raise InputError(f"D's start must be clean or corrupted (with t_max), got {meta.start!r}", where)
        return meta

    def to_config(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @property
    def noise_levels(self) -> int:
        return self.t_max if self.start == "corrupted" and self.t_max is not None else self.train_timesteps
