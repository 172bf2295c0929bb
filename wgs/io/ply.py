"""PLY files with one vertex element of float32 properties, binary little endian: the container
of 3DGS models (the attribute layout is `gaussians.splats`')."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .files import atomic_write_bytes

END_HEADER = b"end_header\n"


def write_ply(path: str | Path, names: list[str], data: np.ndarray) -> None:
    """Atomic write of `data` [N, len(names)] as float32 vertex properties `names`."""
    if data.ndim != 2 or data.shape[1] != len(names):
        raise ValueError(f"data {data.shape} for {len(names)} properties")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(data)}"]
    header += [f"property float {a}" for a in names] + ["end_header"]
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + data.astype("<f4").tobytes())


def read_ply(path: str | Path) -> tuple[list[str], np.ndarray]:
    """(property names, [N, len(names)] float32) of a binary little-endian PLY's vertex element."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read PLY ({exc.strerror})", path) from None
    end = raw.find(END_HEADER)
    if not raw.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path)
    lines = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError("only binary little-endian PLY is supported", path)
    n = next((int(ln.split()[2]) for ln in lines if ln.startswith("element vertex")), None)
    props = [ln.split() for ln in lines if ln.startswith("property")]
    if n is None or any(p[1] != "float" for p in props):
        raise InputError("expected 'element vertex' with float properties", path)
    names = [p[2] for p in props]
    body = raw[end + len(END_HEADER) :]
    if len(body) < n * 4 * len(names):
        raise InputError(f"truncated: {len(body)} bytes for {n} vertices", path)
    return names, np.frombuffer(body, dtype="<f4", count=n * len(names)).reshape(n, len(names))
