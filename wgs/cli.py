"""The `wgs` command line.

Pipeline: prepare -> coarse -> mask-data -> finetune -> repair -> fine -> eval.
Each stage reads and writes one workspace folder and is skipped when its inputs are unchanged.
"""

from __future__ import annotations

import errno
import signal
import sys
from pathlib import Path

import click

from . import __version__
from .cli_options import config_options, preset_option
from .config import as_dict, load_config_file
from .context import Ctx
from .errors import WgsError
from .progress import results, set_quiet
from .resume import Interrupted, install_stop_handlers
from .threads import configure as configure_threads
from .workspace import STAGE_DIRS

HELP = """WaveletGaussian: sparse-view 3D Gaussian object reconstruction.

\b
  prepare    import posed photos (+ masks), or pose photos by structure-from-motion
  coarse     train a coarse 3DGS on the sparse views; Haar-DWT its renders
  mask-data  online random masking -> corrupted/clean LL training pairs
  finetune   train the LL diffusion repair model D and the HF U-Net U
  repair     repair novel-view renders -> pseudo references;  fine: refine on them;  eval: metrics

Every stage reads and writes one workspace (-w) and is skipped when up to date.

\b
Quick start:
  wgs -w my_ws all path/to/scene     # every stage, then the report
  wgs -w my_ws info                  # what the workspace holds
  wgs -w my_ws render --views path   # an orbit of the final model
  wgs -w my_ws view                  # the model in the browser (WebGL, localhost)
  wgs -w my_ws suggest               # where one more photo would help the shape most
"""


class PipelineOrderGroup(click.Group):
    """Commands listed in the order they were added (pipeline order), not alphabetically."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)


@click.group(cls=PipelineOrderGroup, help=HELP,
             context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
@click.option("-w", "--workspace", type=click.Path(path_type=Path), help="Workspace folder.")
@click.option("--device", default=None, help="auto | cpu | cuda[:N] | mps  (auto: cuda, mps, cpu).")
@click.option("--seed", type=int, default=None, help="Random seed (default 0).")
@click.option("--quiet", "-q", is_flag=True, help="Only errors and final results.")
@click.option("--config", "config_file", type=click.Path(path_type=Path), help="wgs.toml: one table per stage.")
@click.option("--debug", is_flag=True, help="Show tracebacks.")
@click.option("--resume", is_flag=True, help="Continue an interrupted stage from its saved state.")
@click.option("--checkpoint-every", type=click.FloatRange(min=0), default=60.0, show_default=True,
              help="Seconds between saved states inside long training loops.")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="CPU threads for torch and numba (default: WGS_THREADS, else the cores this process may use).")
@click.version_option(__version__, prog_name="wgs")
@click.pass_context
def cli(ctx: click.Context, workspace, device, seed, quiet, config_file, debug, resume, checkpoint_every,
        threads) -> None:
    set_quiet(quiet)
    configure_threads(threads)
    file_cfg = load_config_file(config_file) if config_file else {"global": {}}
    g = file_cfg["global"]
    ctx.obj = Ctx(workspace, device or g.get("device", "auto"), seed if seed is not None else g.get("seed", 0),
                  debug, file_cfg, resume, checkpoint_every, config_file)


def workspace_option(f):
    """-w also accepted after the subcommand (`wgs coarse -w WS`)."""
    def set_ws(ctx: click.Context, _param, value):
        if value is not None:
            ctx.find_object(Ctx).workspace = value
        return value

    return click.option("-w", "--workspace", "ws_override", type=click.Path(path_type=Path), expose_value=False,
                        callback=set_ws, help="Workspace folder.")(f)


def stage_common(f):
    f = click.option("--force", is_flag=True, help="Rerun even when up to date.")(f)
    f = preset_option(f)
    return workspace_option(f)


@cli.command()
@click.argument("scene", type=click.Path(path_type=Path))
@config_options("prepare", "views", "downscale", "max_size", "max_pixels", "matcher", "masks", "mask_agreement",
                "mask_voter_support", "mask_colour_ratio", "mask_max_cut", "mask_max_missed", "mirror")
@stage_common
@click.pass_obj
def prepare(obj: Ctx, scene: Path, force, preset, **options) -> None:
    """Import SCENE (COLMAP, Blender, instant-ngp/nerfstudio, IDR, LLFF, or photos without poses,
    which structure-from-motion poses) into the workspace."""
    from .pipeline import prepare_and_estimate

    prepare_and_estimate(obj, scene, preset, options, force)


@cli.command()
@workspace_option
@click.pass_obj
def info(obj: Ctx) -> None:
    """Show what the workspace holds and which stages are done, fresh or stale."""
    from rich.table import Table

    ws = obj.ws()
    if not ws.root.is_dir():
        raise WgsError("workspace folder not found", ws.root)
    m = ws.manifest("scene")
    if m is not None:
        s = m.get("summary", {})
        res = s.get("resolution")
        res_txt = f"{res[0]}x{res[1]}" if res and isinstance(res[0], int) else str(res)
        results.print(f"scene: {s.get('source')} ({s.get('format')})", soft_wrap=True)
        results.print(f"  {s.get('num_train')} training views, {s.get('num_test')} test views, "
                      f"{res_txt} images, {'with' if s.get('has_masks') else 'without'} masks")
    table = Table(title=f"workspace {ws.root}")
    for col in ("stage", "folder", "status", "wall time", "finished"):
        table.add_column(col)
    for stage, folder in STAGE_DIRS.items():
        st = ws.status(stage)
        mm = ws.manifest(stage) or {}
        colour = {"fresh": "green", "stale": "yellow", "missing": "dim"}[st]
        wt = mm.get("wall_time_s")
        table.add_row(stage, folder + "/", f"[{colour}]{st}[/]", f"{wt:.1f} s" if wt is not None else "",
                      mm.get("finished", ""))
    results.print(table)
    from .threads import describe

    t = describe()
    results.print(f"threads: torch {t['torch_threads']}, numba {t['numba_threads']} ({t['numba_layer']}) "
                  f"on {t['cores']} available core(s), {'adaptive' if t['adaptive'] else 'fixed'}")


@cli.command()
@click.option("--resolution", type=click.IntRange(min=16), default=64, show_default=True,
              help="Voxels along the hull's box.")
@workspace_option
@click.pass_obj
def suggest(obj: Ctx, resolution: int) -> None:
    """Say where one more photo would bound most of the shape that no photo bounds now (after
    `wgs prepare`; the scene needs masks): a sentence, and a preview from there in WS/suggest/."""
    from .io import atomic_write_json
    from .io.images import write_png
    from .progress import results
    from .scene.dataset import load_prepared
    from .shape.hull import visual_hull_grid
    from .shape.next_view import loose_voxels, preview, suggest_view

    ws = obj.ws()
    if ws.status("scene") == "missing":
        raise WgsError("no prepared scene: run `wgs prepare SCENE` first", ws.root)
    scene = load_prepared(ws.output("scene", "prepared"))
    if not scene.has_masks:
        raise WgsError("the scene has no masks, and the shape that photos bound comes from masks", ws.root)
    hull = visual_hull_grid(scene.train, resolution, tolerate=0)
    core, loose = loose_voxels(hull)
    record = suggest_view(core, loose, scene.photos)
    out = ws.root / "suggest"
    write_png(out / "preview.png", preview(hull, core, loose, record["camera"]))
    camera = record.pop("camera")
    atomic_write_json(out / "suggestion.json", {**record, "camera": camera.to_json()})
    results.print(f"suggest: one more photo {record['sentence']}: it would bound {record['bounds']:.0%} of the "
                  f"shape no photo bounds now (a median direction: {record['median_bounds']:.0%}); preview "
                  f"{out / 'preview.png'}", soft_wrap=True)


def _register_stages() -> None:
    from . import commands

    commands.register(cli, stage_common, workspace_option)


def global_option_hint(name: str) -> str:
    """Where a global option goes when it was given after the command (`wgs all S --device cpu`)."""
    for p in cli.params:
        if name in getattr(p, "opts", ()) or name in getattr(p, "secondary_opts", ()):
            return f"{name} is a global option: put it before the command, `wgs {name} ... COMMAND ...`"
    return ""


INTERRUPTED = "interrupted: finished stages are kept; `wgs --resume ...` continues from the last saved state"


def main(argv: list[str] | None = None) -> None:
    debug = "--debug" in (argv if argv is not None else sys.argv[1:])
    install_stop_handlers()
    try:
        cli.main(args=argv, prog_name="wgs", standalone_mode=False)
    except (click.exceptions.Abort, KeyboardInterrupt) as exc:
        stop = exc.__cause__ if isinstance(exc, click.exceptions.Abort) else exc  # click wraps the signal's
        click.echo(INTERRUPTED, err=True)
        sys.exit(128 + getattr(stop, "signum", signal.SIGINT))
    except click.NoSuchOption as exc:
        where = global_option_hint(exc.option_name)
        if where:
            exc.message = f"{exc.message} ({where})"
        exc.show()
        sys.exit(exc.exit_code)
    except click.BadParameter as exc:  # an option's value out of its choices or range: one line, like bad files
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(2)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except Interrupted as exc:
        click.echo(f"interrupted: {exc}", err=True)
        sys.exit(128 + exc.signum)
    except WgsError as exc:
        if debug:
            raise
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except OSError as exc:
        if debug:
            raise
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        hint = ("; free some space and rerun (finished stages are kept, `--resume` continues)"
                if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else "")
        click.echo(f"error: {where}{exc.strerror or exc}{hint}", err=True)
        sys.exit(1)


_register_stages()

__all__ = ["cli", "main", "as_dict"]
