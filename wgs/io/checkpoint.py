"""Checkpoint files: a dict of tensors and plain values, written atomically by `torch.save` and
read with `weights_only` (no pickled code runs). What the dict holds is the caller's business."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from .files import atomic_write_bytes


class UnreadableCheckpoint(Exception):
    """The file is missing, damaged, or holds more than tensors and plain values (the reason)."""


def write_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getvalue())


def read_checkpoint(path: str | Path) -> Any:
    """The saved object, tensors on the CPU; `UnreadableCheckpoint` with torch's first line of why."""
    try:
        return torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a damaged file
        first_line = (str(exc).splitlines() or [""])[0][:200]
        raise UnreadableCheckpoint(f"{type(exc).__name__}: {first_line}") from None
