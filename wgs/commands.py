"""Click commands of the stages and tools (apart from cli.py so heavy imports stay lazy)."""

from __future__ import annotations

from pathlib import Path

import click

from .cli_options import config_option, config_options, preset_option
from .config import PRESETS
from .errors import WgsError
from .progress import log

# `wgs all`'s own options: config field -> the stage tables it sets
ALL_FIELDS: dict[str, tuple[str, ...]] = {
    "views": ("prepare",), "downscale": ("prepare",), "max_size": ("prepare",), "matcher": ("prepare",),
    "masks": ("prepare",),
    "mirror": ("prepare",),
    "ensemble": ("coarse",),
    "strategy": ("mask_data",), "domain": ("finetune",), "use_u": ("finetune",), "prior": ("finetune",),
    "carve": ("repair",), "shape_revolution": ("repair",), "shape_smooth": ("repair",),
    "lpips_weights": ("fine", "eval")}


def all_options(f):
    for name, tables in reversed(ALL_FIELDS.items()):
        f = config_option(tables[0], name)(f)
    return f


def all_overrides(options: dict) -> dict[str, dict]:
    """`wgs all`'s option values as per-table overrides of the stages' configs."""
    out: dict[str, dict] = {}
    for name, tables in ALL_FIELDS.items():
        for table in tables:
            out.setdefault(table, {})[name] = options[name]
    return out

model_stage_option = click.option("--stage", "stage", type=click.Choice(["coarse", "fine"]), default=None,
                                  help="Which model (default: the newest, fine when it exists).")


def register(cli, stage_common, workspace_option) -> None:
    """Add the stage subcommands to the `wgs` group."""

    @cli.command()
    @config_options("coarse", "iterations", "max_seconds", "sh_degree", "ensemble")
    @stage_common
    @click.pass_obj
    def coarse(obj, force, preset, **options):
        """Train the coarse 3DGS G_c on the training views."""
        obj.run_stage("coarse", obj.config("coarse", preset, **options), force)

    @cli.command("mask-data")
    @config_options("mask_data", "strategy", "iterations", "n_regions", "coverage")
    @stage_common
    @click.pass_obj
    def mask_data(obj, force, preset, **options):
        """Corrupted/clean pairs for the repair models (trains G_d, or N models for loo)."""
        obj.run_stage("mask_data", obj.config("mask_data", preset, **options), force)

    @cli.command()
    @config_options("finetune", "domain", "use_u", "levels", "d_steps", "diffusion", "sd_model", "controlnet",
                    "u_max_steps", "prior_steps", "prior")
    @stage_common
    @click.pass_obj
    def finetune(obj, force, preset, **options):
        """Fine-tune the repair model D (from the pretrained prior) and the HF U-Net U on this object."""
        obj.run_stage("finetune", obj.config("finetune", preset, **options), force)

    @cli.command()
    @config_options("repair", "poses", "num_views", "strength", "steps", "views_per_train", "carve",
                    "shape_revolution", "shape_smooth")
    @stage_common
    @click.pass_obj
    def repair(obj, force, preset, **options):
        """Render G_c at novel views and repair them with D and U -> pseudo references."""
        obj.run_stage("repair", obj.config("repair", preset, **options), force)

    @cli.command()
    @config_options("fine", "iterations", "rounds", "lpips_weights", "start")
    @stage_common
    @click.pass_obj
    def fine(obj, force, preset, **options):
        """Train G_f on the real and the pseudo references."""
        obj.run_stage("fine", obj.config("fine", preset, **options), force)

    @cli.command("eval")
    @config_options("eval", "lpips_net", "lpips_weights", "max_views", "repair_gain_views")
    @stage_common
    @click.pass_obj
    def eval_(obj, force, preset, **options):
        """PSNR, SSIM, LPIPS and silhouettes of G_f and G_c on the test views, and the error-against-time report."""
        from .stages.shared import newest_model

        obj.run_stage("eval", obj.config("eval", preset, **options), force, final=newest_model(obj.ws()))

    @cli.command()
    @stage_common
    @click.pass_obj
    def baseline(obj, force, preset):
        """Plain 3DGS trained for the pipeline's training time (what that time buys without the repair);
        eval then draws its curve beside the method's."""
        obj.run_stage("baseline", obj.config("baseline", preset), force)

    @cli.command("all")
    @click.argument("scene", type=click.Path(path_type=Path))
    @all_options
    @click.option("--budget", default=None,
                  help="A time budget for the run, such as 10m, 90s or 1h (a bare number is minutes; also [all] "
                       "budget): the working size and the training stages' time are chosen to end within it.")
    @click.option("--force-repair", is_flag=True, help="Run the repair stages even with many training views.")
    @click.option("--baseline", "baseline", is_flag=True,
                  help="Also train plain 3DGS for the same training time and plot its curve (wgs baseline).")
    @stage_common
    @click.pass_obj
    def all_(obj, scene, budget, force_repair, baseline, force, preset, **options):
        """Run every stage on SCENE (each skipped when up to date) and print the summary."""
        from .pipeline import print_summary, run_all

        scene = Path(scene).resolve()  # messages name the folder, not "."
        if obj.workspace is None:  # beside the scene folder: SCENE_wgs (`wgs all .` too)
            if not scene.name:
                raise WgsError("no workspace name for the root folder: pass -w/--workspace DIR")
            obj.workspace = scene.with_name(scene.name + "_wgs")
            log(f"workspace: {obj.workspace}")
        from .estimate import parse_duration

        budget = budget or obj.file_cfg.get("all", {}).get("budget")
        outcomes = run_all(obj, scene, preset, force, force_repair, all_overrides(options),
                           ("baseline",) if baseline else (), parse_duration(budget) if budget else None)
        print_summary(obj.ws(), outcomes)

    @cli.command()
    @click.argument("scenes")
    @click.option("-o", "--output", "root", type=click.Path(path_type=Path), required=True,
                  help="Root folder: ROOT/<scene name>/ workspaces, ROOT/_batch/ logs and summary.")
    @click.option("--executor", type=click.Choice(["local", "slurm"]), default="local", show_default=True,
                  help="local: a process pool; slurm: a job array through submitit (wgs[slurm]).")
    @click.option("-j", "--jobs", type=click.IntRange(min=1), default=None,
                  help="local: scenes at a time (default: one per visible GPU, else 1).")
    @click.option("--rank", type=click.IntRange(min=0), default=None,
                  help="Run only scenes rank, rank+n, ... (default: $SLURM_ARRAY_TASK_ID, else all).")
    @click.option("--world-size", type=click.IntRange(min=1), default=None,
                  help="Number of shards n (default: $SLURM_ARRAY_TASK_COUNT, else 1).")
    @click.option("--preset", type=click.Choice(list(PRESETS)), default=None,
                  help="Budget preset for every scene (a line's own --preset wins).")
    @click.option("--force", is_flag=True, help="Run finished scenes again (their fresh stages are still skipped).")
    @click.option("--summary-only", is_flag=True, help="Only aggregate what the workspaces hold.")
    @click.option("--partition", default=None, help="slurm: partition.")
    @click.option("--time-min", type=click.IntRange(min=1), default=120, show_default=True,
                  help="slurm: time limit per scene (minutes).")
    @click.option("--gpus", type=click.IntRange(min=0), default=0, show_default=True, help="slurm: GPUs per scene.")
    @click.option("--cpus", type=click.IntRange(min=1), default=4, show_default=True, help="slurm: CPUs per scene.")
    @click.option("--mem-gb", type=click.IntRange(min=1), default=None, help="slurm: memory per scene (GB).")
    @click.option("--array-parallelism", type=click.IntRange(min=1), default=32, show_default=True,
                  help="slurm: array elements running at once.")
    @click.option("--cluster", type=click.Choice(["auto", "slurm", "local", "debug"]), default="auto",
                  show_default=True, help="slurm: submitit's executor (local/debug run without a cluster).")
    @click.pass_obj
    def batch(obj, scenes, root, executor, jobs, rank, world_size, preset, force, summary_only, partition, time_min,
              gpus, cpus, mem_gb, array_parallelism, cluster):
        """Run `wgs all` on many scenes. SCENES: a text file (a scene folder per line, optional `wgs all`
        options after it) or a quoted glob of scene folders. Exit status 1 when a scene failed."""
        import sys
        import time

        from . import batch as b

        tasks = b.read_scene_list(scenes, cli.commands["all"])
        if preset:
            tasks = [t if "--preset" in t.options else b.SceneTask(t.name, t.scene, (*t.options, "--preset", preset))
                     for t in tasks]
        root = root.resolve()
        ran: dict = {}
        t0 = time.perf_counter()
        if not summary_only:
            r, n = b.shard_from_env(rank, world_size)
            mine = b.shard(tasks, r, n)
            if n > 1:
                log(f"batch: shard {r} of {n}: {len(mine)} of {len(tasks)} scene(s)")
            args = obj.child_args()
            if executor == "local":
                out = b.run_local(mine, root, args, jobs, obj.device != "cpu", rerun=force)
            else:
                opts = b.SlurmOptions(None if cluster == "auto" else cluster, partition, time_min, gpus, cpus,
                                      mem_gb, array_parallelism)
                out = b.run_submitit(mine, root, args, opts, rerun=force)
            ran = {o["name"]: o for o in out}
        summary = b.summarize(root, tasks, ran)
        if ran:
            summary["batch_wall_time_s"] = round(time.perf_counter() - t0, 1)
        b.write_summary(root, summary)
        b.print_summary(summary)
        log(f"batch: summary in {root / b.BATCH_DIR / 'summary.json'} and summary.csv")
        if any(o["status"] == "failed" for o in ran.values()):
            sys.exit(1)

    @cli.command()
    @click.argument("scene", type=click.Path(path_type=Path))
    @click.option("--rows", default="paper", show_default=True,
                  help="paper | all | comma-separated names (loo-rgb, offline-rgb, orm-rgb, orm-wavelet, "
                       "orm-wavelet-u, 3dgs, orm-wavelet-u-j2).")
    @click.option("--repeats", type=int, default=1, show_default=True, help="Runs per row (seeds seed..seed+K-1).")
    @config_options("prepare", "views", "downscale", "mirror")
    @preset_option
    @workspace_option
    @click.pass_obj
    def ablate(obj, scene, rows, repeats, views, downscale, mirror, preset):
        """The paper's ablation on SCENE: one workspace per row under -w ROOT, and ROOT/ablation.{md,csv,json,png}.
        Every row trains on the same prepared views (--mirror none: the photos alone, as in the paper)."""
        from .ablation import aggregate, parse_rows, run_ablation, write_outputs
        from .progress import results

        if repeats < 1:
            raise click.BadParameter("must be >= 1", param_hint="--repeats")
        root = obj.ws().root
        row_list = parse_rows(rows)
        records = run_ablation(obj, scene, root, row_list, repeats, preset, {"views": views, "downscale": downscale,
                                                                               "mirror": mirror})
        write_outputs(root, aggregate(records, row_list), records)
        results.print((root / "ablation.md").read_text())

    @cli.command()
    @model_stage_option
    @click.option("--views", type=click.Choice(["test", "train", "path"]), default="test", help="Cameras to render.")
    @click.option("--frames", type=int, default=60, help="Number of frames for --views path.")
    @click.option("--video", is_flag=True,
                  help="Also write the frames as an animated GIF (a turntable with --views path).")
    @workspace_option
    @click.pass_obj
    def render(obj, stage, views, frames, video):
        """Render a trained model to PNGs under WS/renders/STAGE_VIEWS/."""
        from .stages.render_views import run_render
        from .stages.shared import newest_model

        ws = obj.ws()
        run_render(ws, stage or newest_model(ws), views, frames, obj.torch_device(), video)

    @cli.command()
    @model_stage_option
    @click.option("--port", type=click.IntRange(0, 65535), default=8765, help="Port on 127.0.0.1 (0: any free one).")
    @click.option("--no-browser", is_flag=True, help="Print the address only; do not open a browser.")
    @workspace_option
    @click.pass_obj
    def view(obj, stage, port, no_browser):
        """Look at the model in the browser: a WebGL splat viewer on 127.0.0.1 (Ctrl-C stops it)."""
        import time
        import webbrowser

        from .progress import results
        from .viewer import serving, site

        ws = obj.ws()
        if not ws.root.is_dir():
            raise WgsError("workspace folder not found", ws.root)
        files = site(ws, stage)
        with serving(files, port) as url:
            results.print(f"viewer: {url}  (report: {url}report.html)" if "/report.html" in files else f"viewer: {url}")
            results.print("Ctrl-C stops it")
            if not no_browser:
                webbrowser.open(url)
            while True:
                time.sleep(3600)

    @cli.command()
    @model_stage_option
    @click.option("--format", "fmt", type=click.Choice(["ply", "splat"]), default="ply",
                  help="ply: INRIA 3DGS layout, SH degree 3 (SIBR and most viewers); splat: antimatter15's "
                       "compact layout for WebGL viewers (no view-dependent colour).")
    @click.option("-o", "--output", type=click.Path(path_type=Path), default=None,
                  help="Output file (default: WS/export/STAGE.FORMAT).")
    @workspace_option
    @click.pass_obj
    def export(obj, stage, fmt, output):
        """Write the model for other viewers and tools (world coordinates of the input scene)."""
        from .gaussians.splats import SPLAT_ROW, VIEWER_SH_DEGREE, export_ply, load_checkpoint, splat_bytes
        from .io import atomic_write_bytes
        from .progress import results
        from .viewer import model_path

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
