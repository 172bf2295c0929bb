"""The `wgs` group: the global options, the error mapping of the entry point (`main`), and what
the commands share (`workspace_option`, `stage_common`). The commands are in the other modules
of this package."""

from __future__ import annotations

import errno
import os
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

import click

from .. import __version__
from ..config import load_config_file
from ..context import RunOptions
from ..errors import WgsError
from ..fields import facts, option
from ..progress import set_quiet
from ..resume import Interrupted, install_stop_handlers
from ..threads import configure as configure_threads
from .options import PresetChoice, settings_options

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


@dataclass
class GlobalSettings:
    """The options every command shares, given before it (`wgs -w WS COMMAND`)."""

    workspace: Path | None = option(None, "Workspace folder.", flags=("-w", "--workspace"))
    device: str | None = option(None, "auto | cpu | cuda[:N] | mps  (auto: cuda, mps, cpu).")
    seed: int | None = option(None, "Random seed (default 0).")
    quiet: bool = option(False, "Only errors and final results.", flags=("--quiet", "-q"))
    config_file: Path | None = option(None, "wgs.toml: one table per stage.", flags=("--config",))
    debug: bool = option(False, "Show tracebacks.")
    resume: bool = option(False, "Continue an interrupted stage from its saved state.")
    checkpoint_every: float = option(60.0, "Seconds between saved states inside long training loops.", bounds=(0, None))
    threads: int | None = option(
        None,
        "CPU threads for torch and numba (default: WGS_THREADS, else the cores this process may use).",
        bounds=(1, None),
    )


class PipelineOrderGroup(click.Group):
    """Commands listed in the order they were added (pipeline order), not alphabetically."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)


@click.group(
    cls=PipelineOrderGroup, help=HELP, context_settings={"help_option_names": ["-h", "--help"], "show_default": True}
)
@settings_options(GlobalSettings)
@click.version_option(__version__, prog_name="wgs")
@click.pass_context
def cli(
    ctx: click.Context, workspace, device, seed, quiet, config_file, debug, resume, checkpoint_every, threads
) -> None:
    set_quiet(quiet)
    configure_threads(threads)
    file_cfg = load_config_file(config_file) if config_file else {"global": {}}
    g = file_cfg["global"]
    started = ctx.obj  # main()'s list, which learns the run's options for its crash log
    ctx.obj = RunOptions(
        workspace,
        device or g.get("device", "auto"),
        seed if seed is not None else g.get("seed", 0),
        debug,
        file_cfg,
        resume,
        checkpoint_every,
        config_file,
    )
    if isinstance(started, list):
        started.append(ctx.obj)


def workspace_option(f):
    """-w also accepted after the subcommand (`wgs coarse -w WS`)."""

    def set_ws(ctx: click.Context, _param, value):
        obj = ctx.find_object(RunOptions)
        if value is not None and obj is not None:
            obj.workspace = value
        return value

    return click.option(
        "-w",
        "--workspace",
        "ws_override",
        type=click.Path(path_type=Path),
        expose_value=False,
        callback=set_ws,
        help=facts(GlobalSettings, "workspace")["help"],
    )(f)


@dataclass
class StageRunSettings(PresetChoice):
    """What every stage command takes besides its own options."""

    force: bool = option(False, "Rerun even when up to date.")


def stage_common(f):
    return workspace_option(settings_options(StageRunSettings)(f))


def global_option_hint(name: str) -> str:
    """Where a global option goes when it was given after the command (`wgs all S --device cpu`)."""
    for p in cli.params:
        if name in getattr(p, "opts", ()) or name in getattr(p, "secondary_opts", ()):
            return f"{name} is a global option: put it before the command, `wgs {name} ... COMMAND ...`"
    return ""


INTERRUPTED = "interrupted: finished stages are kept; `wgs --resume ...` continues from the last saved state"


def crash_log(exc: BaseException, args: list[str], options: RunOptions | None) -> Path:
    """Write `exc`'s traceback, the command line and the versions to a log file: in the run's
    workspace (WS/logs/) where it has one, else in the cache ($WGS_CACHE, default ~/.cache/wgs).
    Returns its path."""
    import datetime
    import platform
    import traceback

    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    text = (
        f"wgs {__version__}, Python {platform.python_version()}, {platform.platform()}\n"
        f"command: wgs {' '.join(args)}\n\n" + "".join(traceback.format_exception(exc))
    )
    folders = [options.workspace / "logs"] if options is not None and options.workspace is not None else []
    folders.append(Path(os.environ.get("WGS_CACHE") or Path.home() / ".cache" / "wgs") / "logs")
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / f"error-{stamp}-{os.getpid()}.log"
            path.write_text(text)
            return path
        except OSError:
            continue
    raise exc


def main(argv: list[str] | None = None) -> None:
    args = list(argv if argv is not None else sys.argv[1:])
    debug = "--debug" in args or os.environ.get("WGS_DEBUG", "0") not in ("", "0")
    install_stop_handlers()
    started: list[RunOptions] = []
    try:
        cli.main(args=args, prog_name="wgs", standalone_mode=False, obj=started)
    except (click.exceptions.Abort, KeyboardInterrupt) as exc:
        stop = exc.__cause__ if isinstance(exc, click.exceptions.Abort) else exc  # click wraps the signal's
        click.echo(INTERRUPTED, err=True)
        sys.exit(128 + getattr(stop, "signum", signal.SIGINT))
    except click.NoSuchOption as exc:
        where = global_option_hint(exc.option_name)
        if where:
            exc = click.NoSuchOption(exc.option_name, f"{exc.message} ({where})", exc.possibilities, exc.ctx)
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
        hint = (
            "; free some space and rerun (finished stages are kept, `--resume` continues)"
            if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
            else ""
        )
        click.echo(f"error: {where}{exc.strerror or exc}{hint}", err=True)
        sys.exit(1)
    except Exception as exc:  # a bug: one line, the traceback in a log file (--debug or WGS_DEBUG=1 shows it)
        if debug:
            raise
        path = crash_log(exc, args, started[-1] if started else None)
        what = " ".join(str(exc).split())[:200]
        click.echo(
            f"error: unexpected {type(exc).__name__}: {what} (a bug in wgs, please report it; details in {path}; "
            "--debug shows them here)",
            err=True,
        )
        sys.exit(1)
