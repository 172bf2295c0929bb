"""`wgs batch`: `wgs all` on many scenes, locally or on Slurm."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import click

from ..config import PRESETS
from ..fields import option
from ..progress import log
from .main import cli
from .options import settings_options


@dataclass
class BatchSettings:
    root: Path = option(
        None,
        "Root folder: ROOT/<scene name>/ workspaces, ROOT/_batch/ logs and summary.",
        flags=("-o", "--output"),
        required=True,
    )
    executor: str = option(
        "local", "local: a process pool; slurm: a job array through submitit (wgs[slurm]).", choices=("local", "slurm")
    )
    jobs: int | None = option(
        None,
        "local: scenes at a time (default: one per visible GPU, else 1).",
        bounds=(1, None),
        flags=("-j", "--jobs"),
    )
    rank: int | None = option(
        None, "Run only scenes rank, rank+n, ... (default: $SLURM_ARRAY_TASK_ID, else all).", bounds=(0, None)
    )
    world_size: int | None = option(
        None, "Number of shards n (default: $SLURM_ARRAY_TASK_COUNT, else 1).", bounds=(1, None)
    )
    preset: str | None = option(
        None, "Budget preset for every scene (a line's own --preset wins).", choices=tuple(PRESETS)
    )
    force: bool = option(False, "Run finished scenes again (their fresh stages are still skipped).")
    summary_only: bool = option(False, "Only aggregate what the workspaces hold.")
    partition: str | None = option(None, "slurm: partition.")
    time_min: int = option(120, "slurm: time limit per scene (minutes).", bounds=(1, None))
    gpus: int = option(0, "slurm: GPUs per scene.", bounds=(0, None))
    cpus: int = option(4, "slurm: CPUs per scene.", bounds=(1, None))
    mem_gb: int | None = option(None, "slurm: memory per scene (GB).", bounds=(1, None))
    array_parallelism: int = option(32, "slurm: array elements running at once.", bounds=(1, None))
    signal_s: int = option(
        90,
        "slurm: seconds before the time limit at which Slurm signals a job: it saves, stops and is requeued.",
        bounds=(1, None),
    )
    requeues: int = option(
        3, "slurm: times a job stopped at its time limit is requeued (preemption: always).", bounds=(0, None)
    )
    cluster: str = option(
        "auto",
        "slurm: submitit's executor (local/debug run without a cluster).",
        choices=("auto", "slurm", "local", "debug"),
    )


def all_options_check(all_command: click.Command) -> Callable[[Path, list[str]], str | None]:
    """`batch.read_scene_list`'s check of a scene's options: how `wgs all` parses them."""

    def check(scene: Path, options: list[str]) -> str | None:
        try:
            all_command.make_context("all", [str(scene), *options], resilient_parsing=False)
        except click.ClickException as exc:
            return exc.format_message()
        return None

    return check


@click.command()
@click.argument("scenes")
@settings_options(BatchSettings)
@click.pass_obj
def batch(obj, scenes: str, **settings) -> None:
    """Run `wgs all` on many scenes. SCENES: a text file (a scene folder per line, optional `wgs all`
    options after it) or a quoted glob of scene folders. Exit status 1 when a scene failed."""
    import dataclasses
    import sys
    import time

    from .. import batch as b

    cfg = BatchSettings(**settings)
    tasks = b.read_scene_list(scenes, all_options_check(cli.commands["all"]))
    if cfg.preset:
        tasks = [
            t if "--preset" in t.options else b.SceneTask(t.name, t.scene, (*t.options, "--preset", cfg.preset))
            for t in tasks
        ]
    root = cfg.root.resolve()
    ran: dict = {}
    t0 = time.perf_counter()
    if not cfg.summary_only:
        r, n = b.shard_from_env(cfg.rank, cfg.world_size)
        mine = b.shard(tasks, r, n)
        if n > 1:
            log(f"batch: shard {r} of {n}: {len(mine)} of {len(tasks)} scene(s)")
        args = obj.child_args()
        if cfg.executor == "local":
            out = b.run_local(mine, root, args, cfg.jobs, obj.device != "cpu", rerun=cfg.force)
        else:
            slurm = {f.name: settings[f.name] for f in dataclasses.fields(b.SlurmOptions)}
            opts = b.SlurmOptions(**{**slurm, "cluster": None if cfg.cluster == "auto" else cfg.cluster})
            out = b.run_submitit(mine, root, args, opts, rerun=cfg.force)
        ran = {o["name"]: o for o in out}
    summary = b.summarize(root, tasks, ran)
    if ran:
        summary["batch_wall_time_s"] = round(time.perf_counter() - t0, 1)
    b.write_summary(root, summary)
    b.print_summary(summary)
    log(f"batch: summary in {root / b.BATCH_DIR / 'summary.json'} and summary.csv")
    if any(o["status"] == "failed" for o in ran.values()):
        sys.exit(1)
