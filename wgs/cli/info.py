"""`wgs info`: what a workspace holds."""

from __future__ import annotations

import click

from ..context import RunOptions
from ..errors import WgsError
from ..progress import results
from ..workspace import STAGE_DIRS
from .main import workspace_option


@click.command()
@workspace_option
@click.pass_obj
def info(obj: RunOptions) -> None:
    """Show what the workspace holds and which stages are done, fresh or stale."""
    from rich.table import Table

    ws = obj.ws()
    if not ws.root.is_dir():
        raise WgsError("workspace folder not found", ws.root)
    m = ws.manifest("prepare")
    if m is not None:
        s = m.get("summary", {})
        res = s.get("resolution")
        res_txt = f"{res[0]}x{res[1]}" if res and isinstance(res[0], int) else str(res)
        results.print(f"scene: {s.get('source')} ({s.get('format')})", soft_wrap=True)
        results.print(
            f"  {s.get('num_train')} training views, {s.get('num_test')} test views, "
            f"{res_txt} images, {'with' if s.get('has_masks') else 'without'} masks"
        )
    table = Table(title=f"workspace {ws.root}")
    for col in ("stage", "folder", "status", "wall time", "finished"):
        table.add_column(col)
    for stage, folder in STAGE_DIRS.items():
        st = ws.status(stage)
        mm = ws.manifest(stage) or {}
        colour = {"fresh": "green", "stale": "yellow", "missing": "dim"}[st]
        wt = mm.get("wall_time_s")
        table.add_row(
            stage, folder + "/", f"[{colour}]{st}[/]", f"{wt:.1f} s" if wt is not None else "", mm.get("finished", "")
        )
    results.print(table)
    from ..threads import describe

    t = describe()
    results.print(
        f"threads: torch {t['torch_threads']}, numba {t['numba_threads']} ({t['numba_layer']}) "
        f"on {t['cores']} available core(s), {'adaptive' if t['adaptive'] else 'fixed'}"
    )
