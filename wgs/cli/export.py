"""`wgs export`: the model for other viewers and tools."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click

from ..fields import option
from .main import workspace_option
from .options import ModelChoice, settings_options


@dataclass
class ExportSettings(ModelChoice):
    fmt: str = option(
        "ply",
        "ply: INRIA 3DGS layout, SH degree 3 (SIBR and most viewers); splat: antimatter15's compact layout for "
        "WebGL viewers (no view-dependent colour).",
        choices=("ply", "splat"),
        flags=("--format",),
    )
    output: Path | None = option(None, "Output file (default: WS/export/STAGE.FORMAT).", flags=("-o", "--output"))


@click.command()
@settings_options(ExportSettings)
@workspace_option
@click.pass_obj
def export(obj, stage, fmt, output):
    """Write the model for other viewers and tools (world coordinates of the input scene)."""
    from ..gaussians.splats import SPLAT_ROW, VIEWER_SH_DEGREE, export_ply, load_checkpoint, splat_bytes
    from ..io import atomic_write_bytes
    from ..progress import results
    from ..viewer import model_path

    ws = obj.ws()
    stage, ckpt = model_path(ws, stage)
    splats, _ = load_checkpoint(ckpt)  # world coordinates
    out = output or ws.root / "export" / f"{stage}.{fmt}"
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "ply":
        n = export_ply(out, splats, pad_to_degree=VIEWER_SH_DEGREE)
    else:
        data = splat_bytes(splats)
        atomic_write_bytes(out, data)
        n = len(data) // SPLAT_ROW
    results.print(f"export: {n} Gaussians of the {stage} model -> {out}")
