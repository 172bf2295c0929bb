"""Benchmarks (not tests): `python -m tools.bench rasterizer|iteration|knn|pipeline|batch|contention|sfm|shape`
(see --help).

The rasterizer benchmark times our numba fast path and the pure-torch reference in the same run
on random scenes with realistic footprints (a few px to tens of px), forward and forward+backward,
median and spread over repeats, plus peak memory (RSS) of the process.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import click
import torch

from wgs.gaussians.synthetic import time_backend
from wgs.scene.dataset import load_prepared
from wgs.workspace import STAGE_DIRS, Workspace, peak_memory_mb

CASES = ((128, 10_000), (256, 50_000))


def bench_rasterizer(repeats: int, ref_repeats: int) -> dict:
    rows = []
    for size, n in CASES:
        fast = time_backend("numba", size, n, repeats)
        ref = time_backend("torch", size, n, ref_repeats)
        rows.append(
            {
                "size": size,
                "gaussians": n,
                "numba": fast,
                "torch_reference": ref,
                "speedup_forward_backward": ref["forward_backward"]["median_s"] / fast["forward_backward"]["median_s"],
            }
        )
    return {
        "benchmark": "rasterizer",
        "machine": {"platform": platform.platform(), "cpus": torch.get_num_threads(), "torch": torch.__version__},
        "cases": rows,
        "peak_memory_mb": peak_memory_mb(),
    }


def wgs_cli(*args: str) -> float:
    """Run `wgs ARGS` in a subprocess; returns its wall time."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "wgs", "-q", *args], check=True)
    return time.perf_counter() - t0


def bench_pipeline(scene: str, root: str, preset: str, views: int, downscale: int) -> dict:
    """`wgs all` on a scene, then plain 3DGS (the coarse trainer, no repair) on the same views for the
    same total wall time, both evaluated on all test views; plus mask-data ORM vs LOO, one after the other."""
    base = Path(root)
    if base.exists():
        shutil.rmtree(base)
    ws, ws_loo = base / "wgs", base / "loo"
    pre = ["--preset", preset]
    t_all = wgs_cli("-w", str(ws), "all", scene, "--views", str(views), "--downscale", str(downscale), *pre)
    res = json.loads(Workspace(ws).output("eval", "results").read_text())
    # plain 3DGS for the training time of the stages just run (`wgs baseline`), scored by eval beside them
    t_3dgs = wgs_cli("-w", str(ws), "baseline", *pre)
    wgs_cli("-w", str(ws), "eval", *pre)
    res_3dgs = json.loads(Workspace(ws).output("eval", "results").read_text())["baseline_3dgs"]
    # leave-one-out pairs on the same coarse model, timed right after ORM's (recorded by `wgs all`)
    ws_loo.mkdir(parents=True)
    for d in (STAGE_DIRS["prepare"], STAGE_DIRS["coarse"]):
        shutil.copytree(ws / d, ws_loo / d)
    wgs_cli("-w", str(ws_loo), "mask-data", "--strategy", "loo", *pre)
    orm = Workspace(ws).finished("mask_data")
    loo = Workspace(ws_loo).finished("mask_data")
    ft = Workspace(ws).finished("finetune")
    pick = ("psnr", "psnr_std", "ssim", "ssim_std", "lpips", "lpips_std", "num_gaussians", "num_views")
    return {
        "benchmark": "pipeline",
        "scene": scene,
        "preset": preset,
        "views": views,
        "downscale": downscale,
        "wgs_all_wall_s": t_all,
        "stage_times_s": res["stage_times_s"],
        "coarse": {k: res["coarse"].get(k) for k in pick},
        "fine": {k: res.get(k) for k in pick},
        "plain_3dgs": {**{k: res_3dgs.get(k) for k in pick}, "wall_s": t_3dgs},
        "mask_data": {
            "orm_s": orm["strategy_seconds"],
            "loo_s": loo["strategy_seconds"],
            "ratio_orm_over_loo": orm["strategy_seconds"] / loo["strategy_seconds"],
            "orm_pairs": orm["num_pairs"],
            "loo_pairs": loo["num_pairs"],
        },
        "finetune": {
            k: ft.get(k)
            for k in (
                "d_seconds",
                "d_final_loss",
                "u_seconds",
                "u_best_val",
                "u_identity_val",
                "u_stopped_at",
                "heldout",
            )
        },
        "machine": {"platform": platform.platform(), "threads": torch.get_num_threads()},
    }


def bench_batch(root: str, preset: str, seeds: tuple[int, ...] = (0, 1, 2), jobs: int = 2) -> dict:
    """`wgs batch` over the bundled example generated with three seeds: --jobs N against --jobs 1
    (sequential), one after the other in fresh roots."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from make_scene import make_scene

    base = Path(root) / "batch"
    if base.exists():
        shutil.rmtree(base)
    lines = [str(make_scene(base / "scenes" / f"example_seed{s}", seed=s)) for s in seeds]
    (base / "scenes.txt").write_text("\n".join(lines) + "\n")
    walls = {}
    for n in (jobs, 1):
        t0 = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "wgs",
                "batch",
                str(base / "scenes.txt"),
                "-o",
                str(base / f"jobs{n}"),
                "--jobs",
                str(n),
                "--preset",
                preset,
            ],
            check=True,
        )
        walls[n] = time.perf_counter() - t0
    summary = json.loads((base / f"jobs{jobs}" / "_batch" / "summary.json").read_text())
    return {
        "benchmark": "batch",
        "preset": preset,
        "scenes": len(seeds),
        "jobs": jobs,
        "wall_s": {f"jobs{n}": round(w, 1) for n, w in walls.items()},
        "speedup": walls[1] / walls[jobs],
        "mean": summary["mean"],
        "std": summary["std"],
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }


def timed_coarse_runs(
    prepared: Path, root: Path, iterations: int, copies: int, env: dict[str, str | None]
) -> list[float]:
    """`wgs coarse` for `iterations` on `copies` copies of a prepared workspace, started together;
    wall time of each. env: variables to set (None: unset) in the children."""
    cfg = root / "coarse.toml"
    cfg.write_text(f"[coarse]\niterations = {iterations}\nrefine_stop = {iterations}\nensemble = 1\n")
    procs = []
    for i in range(copies):
        ws = root / f"ws{i}"
        if ws.exists():
            shutil.rmtree(ws)
        ws.mkdir(parents=True)
        shutil.copytree(Workspace(prepared).stage_dir("prepare"), Workspace(ws).stage_dir("prepare"))
    for i in range(copies):
        cmd = [sys.executable, "-m", "wgs", "-q", "--config", str(cfg), "-w", str(root / f"ws{i}"), "coarse"]
        child = {k: v for k, v in {**os.environ, **env}.items() if v is not None}
        procs.append((time.perf_counter(), subprocess.Popen(cmd, env=child)))
    walls = []
    for t0, p in procs:
        if p.wait() != 0:
            raise RuntimeError(f"wgs coarse failed ({p.returncode})")
        walls.append(time.perf_counter() - t0)
    return walls


# thread settings compared by `contention`: wgs's own (threads.py) against the runtimes' defaults
CONTENTION_VARIANTS: dict[str, dict[str, str | None]] = {
    "wgs (adaptive)": {},
    "fixed threads": {"WGS_THREADS": str(os.cpu_count() or 1)},  # all cores, spinning: what wgs did before
    "numba workqueue": {"NUMBA_THREADING_LAYER": "workqueue"},
    "one thread": {"WGS_THREADS": "1"},
}


def bench_contention(prepared: str, root: str, iterations: int, variants: tuple[str, ...]) -> dict:
    """Two `wgs coarse` runs started together against one alone, per thread setting: the slowdown
    a user sees when wgs shares the machine. One after the other, nothing else running."""
    base = Path(root) / "contention"
    base.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in variants:
        env = CONTENTION_VARIANTS[name]
        solo = timed_coarse_runs(Path(prepared), base, iterations, 1, env)[0]
        pair = timed_coarse_runs(Path(prepared), base, iterations, 2, env)
        rows.append(
            {
                "threads": name,
                "env": env,
                "solo_s": round(solo, 1),
                "pair_s": [round(w, 1) for w in pair],
                "slowdown": round(max(pair) / solo, 2),
            }
        )
    return {
        "benchmark": "contention",
        "iterations": iterations,
        "rows": rows,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }


def bench_knn(sizes: tuple[int, ...] = (100_000, 1_000_000), reference_up_to: int = 100_000) -> dict:
    """Mean 3-NN distance (scale init, floater removal): scipy's KD-tree against the brute-force
    torch reference (run only up to `reference_up_to` points: it is O(N^2))."""
    from wgs.gaussians.init import knn_mean_distance, knn_mean_distance_torch

    rows = []
    for n in sizes:
        pts = torch.randn(n, 3, generator=torch.Generator().manual_seed(0)) * 0.3
        t0 = time.perf_counter()
        d = knn_mean_distance(pts, 3)
        row = {"points": n, "kdtree_s": round(time.perf_counter() - t0, 3)}
        if n <= reference_up_to:
            t0 = time.perf_counter()
            ref = knn_mean_distance_torch(pts, 3)
            row["torch_s"] = round(time.perf_counter() - t0, 3)
            row["speedup"] = round(row["torch_s"] / row["kdtree_s"], 1)
            row["max_abs_diff"] = float((d - ref).abs().max())
        rows.append(row)
    return {"benchmark": "knn", "rows": rows, "threads": torch.get_num_threads()}


def bench_sfm(scene: str, root: str, matcher: str = "auto", max_image_size: int = 1600) -> dict:
    """Pose a scene that ships its own poses again from its photos alone (structure-from-motion,
    `wgs prepare`'s path) and compare after a similarity alignment: rotation error (degrees) and
    camera-centre error (share of the scene's camera extent), the focal length over the scene's,
    photos registered, time."""
    import numpy as np

    from wgs.scene.colmap import read_colmap_scene
    from wgs.scene.formats import read_scene
    from wgs.scene.pose_error import pose_errors
    from wgs.scene.sfm import pose_photos
    from wgs.threads import thread_count

    ref = read_scene(scene)
    photos = sorted(ref.views, key=lambda v: v.name)
    folder = Path(root) / "sfm_photos"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    # the photos alone, flat, under the scene's names for them (a split's files may share names)
    flat = {v.name: v.name.replace("/", "_") for v in photos}
    for v in photos:
        shutil.copy2(v.image, folder / flat[v.name])
    out = Path(root) / "sfm_model"
    res = pose_photos(folder, list(flat.values()), None, out, matcher, max_image_size, thread_count())

    posed = {v.name: v for v in read_colmap_scene(folder, out, folder, fmt="photos").views}
    both = [v for v in photos if flat[v.name] in posed]
    err = pose_errors(np.stack([posed[flat[v.name]].w2c for v in both]), np.stack([v.w2c for v in both]))
    rot, cen = np.asarray(err["rotation_deg"]), np.asarray(err["center"]) * 100
    focal = np.array([posed[flat[v.name]].K[0, 0] / v.K[0, 0] for v in both])
    return {
        "benchmark": "sfm",
        "scene": scene,
        "photos": len(photos),
        "registered": res.registered,
        "registered_share": round(res.registered / len(photos), 3),
        "matcher": res.matcher,
        "seconds": round(res.seconds, 1),
        "threads": thread_count(),
        "rotation_deg": {"median": round(float(np.median(rot)), 3), "max": round(float(rot.max()), 3)},
        "center_pct_extent": {"median": round(float(np.median(cen)), 3), "max": round(float(cen.max()), 3)},
        "focal_over_true": {"median": round(float(np.median(focal)), 4)},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }


SHAPE_OBJECTS = (
    "common-3d-test-models-cow",
    "common-3d-test-models-teapot",
    "common-3d-test-models-rocker-arm",
    "common-3d-test-models-homer",
)


S_THRESHOLDS = (0.1, 0.3, 0.5)


def silhouette_knowledge(ws: Workspace, thresholds: tuple[float, ...] = S_THRESHOLDS) -> dict:
    """What S knows at the test views (which it never sees in the pipeline): its silhouette's IoU
    (object probability > 0.5) beside the strict hull's and G_c's opacity's (> 0.5), and for each
    threshold t the share of the hull's excess where S says under t (what carving at t could
    remove) against the share of the true object there (what it would wrongly remove)."""
    from wgs.gaussians.splats import load_checkpoint
    from wgs.gaussians.trainer import render_frame
    from wgs.shape.hull import silhouette
    from wgs.shape.scores import silhouette_scores
    from wgs.stages.repair.run import shape_models
    from wgs.stages.repair.settings import RepairConfig
    from wgs.stages.shared import background_for

    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    device = torch.device("cpu")
    shape = shape_models(scene, RepairConfig(), device)
    frames = [f for f in scene.test if f.mask is not None]
    if shape is None or shape.silhouette_model is None or not frames:
        return {}
    gc, bg = load_checkpoint(ws.output("coarse", "model"), scene.norm, device)[0], background_for(scene)
    iou: dict[str, list[float]] = {"S": [], "hull": [], "coarse": []}
    excess = {t: 0 for t in thresholds}
    lost = {t: 0 for t in thresholds}
    total_excess = total_true = 0
    for f in frames:
        rgb, alpha = render_frame(gc, f, device, bg)
        prob = shape.predict(f, rgb, alpha)
        true, hull = f.object_pixels, silhouette(shape.grid, f)[0]
        for k, sil in (("S", prob > 0.5), ("hull", hull), ("coarse", alpha[..., 0] > 0.5)):
            iou[k].append(silhouette_scores(sil, true)["iou"])
        total_excess += int((hull & ~true).sum())
        total_true += int(true.sum())
        for t in thresholds:
            excess[t] += int((hull & ~true & (prob < t)).sum())
            lost[t] += int((true & (prob < t)).sum())
    return {
        "iou": {k: sum(v) / len(v) for k, v in iou.items()},
        "under": {
            str(t): {"hull_excess": excess[t] / max(total_excess, 1), "object": lost[t] / max(total_true, 1)}
            for t in thresholds
        },
    }


SHAPE_RUNS = {"no-prior": ("--mirror", "none", "--no-carve"), "prior": ()}
"""`bench shape`'s two runs per object: no shape prior at all, and the defaults (mirror views where the
mirror check passes, V and S carving)."""


def bench_shape(
    mirror: str, root: str, objects: tuple[str, ...], preset: str, views: int, size: int = 200, n_test: int = 32
) -> dict:
    """The shape prior on against off on meshes the silhouette model never saw: each rendered by the
    corpus code (24 photos on the upper hemisphere, `n_test` test views over the whole sphere), then
    `wgs all` once per `SHAPE_RUNS` entry. G_f's PSNR and silhouette IoU per object, the hull's
    leave-one-out estimate, what S knows at the test views (`silhouette_knowledge`), and the mean
    gains."""
    from tools.prior.corpus import build_object, extract, list_objects, snapshot_dir

    base = Path(root)
    src = base / "src"
    for repo in sorted({"alecjacobson/common-3d-test-models", "odedstein/meshes"}):
        git_dir = snapshot_dir(Path(mirror), repo)
        if git_dir is not None and not (src / repo.replace("/", "+")).is_dir():
            extract(git_dir, src / repo.replace("/", "+"))
    listed = {o["name"]: o for o in list_objects(src)}
    rows = []
    for name in objects:
        if name not in listed:
            print(f"shape: {name} not in the fetched snapshots under {mirror}: skipped")
            continue
        scene = base / "scenes" / name
        if not (scene / "object.json").is_file():
            build_object(listed[name], src, scene, size, 24, n_test, novel_elevations=(-85.0, 85.0))
        row: dict = {"object": name}
        for run, args in SHAPE_RUNS.items():
            ws = Workspace(base / name / run)
            t = wgs_cli("-w", str(ws.root), "all", str(scene), "--views", str(views), "--preset", preset, *args)
            res = json.loads(ws.output("eval", "results").read_text())
            row[run] = {
                "psnr": res["psnr"],
                "silhouette_iou": res.get("silhouette_iou"),
                "coarse_psnr": res["coarse"]["psnr"],
                "wall_s": round(t, 1),
                "mirror_views": bool(
                    (json.loads(ws.output("prepare", "info").read_text()).get("mirror") or {}).get("used")
                ),
                "carving": ws.finished("repair").get("carving"),
            }
            shape = res.get("shape") or {}
            row["leave_one_out_iou"] = (shape.get("leave_one_out") or {}).get("iou")
            row["hull_test_iou"] = (shape.get("hull_test") or {}).get("iou")
        row["gain_db"] = row["prior"]["psnr"] - row["no-prior"]["psnr"]
        row["s_at_test_views"] = silhouette_knowledge(Workspace(base / name / "no-prior"))
        rows.append(row)
        print(
            f"shape: {name}: G_f {row['no-prior']['psnr']:.2f} -> {row['prior']['psnr']:.2f} dB, silhouette IoU "
            f"{row['no-prior']['silhouette_iou']:.3f} -> {row['prior']['silhouette_iou']:.3f}"
        )
    gains = [r["gain_db"] for r in rows]
    return {
        "benchmark": "shape",
        "preset": preset,
        "views": views,
        "size": size,
        "objects": rows,
        "mean_gain_db": sum(gains) / len(gains) if gains else None,
        "machine": {"platform": platform.platform(), "threads": torch.get_num_threads()},
    }


PHASES = ("wgs:render", "wgs:loss", "wgs:pseudo_view", "wgs:backward", "wgs:adam", "wgs:finite_check", "wgs:densify")
INNER = {
    "wgs:render": ("wgs:project", "wgs:sh", "wgs:raster"),
    "wgs:backward": ("RasterizeNumbaBackward", "ProjectNumbaBackward"),
}


def bench_iteration(
    scene: str,
    root: str,
    views: int,
    downscale: int,
    window: int = 200,
    seed: int = 0,
    stage: str = "coarse",
    workspace: str | None = None,
    start: int | None = None,
) -> dict:
    """Where a training iteration's time goes at the scene's real size, profiled (torch.profiler,
    CPU) over `window` iterations in the middle of the stage's own training with its own settings:
    G_c's (`stage` coarse, on `scene` prepared under `root`) or G_f's (`stage` fine, on `workspace`,
    whose repair stage has run). The rows are the trainer's phase labels (render = projection + SH +
    rasterizer forward, loss = L1 + SSIM + mask, the pseudo view's render and loss, backward with
    the rasterizer's and the projection's own backward, Adam, the finite check, densification);
    "rest" is the loop's Python and bookkeeping. start: the window's first iteration (default: the
    middle of the stage's iterations)."""
    from torch.profiler import ProfilerActivity, profile

    from wgs.config import resolve
    from wgs.gaussians.trainer import train_gaussians
    from wgs.stages.registry import run_stage
    from wgs.stages.shared import initial_splats
    from wgs.stages.stage import StageEnv

    device = torch.device("cpu")
    cfg = resolve(stage)
    if stage == "fine":
        from wgs.stages.fine.run import fine_inputs

        if workspace is None:
            raise SystemExit("iteration --stage fine needs --workspace (a workspace after `wgs repair`)")
        ws = Workspace(Path(workspace))
        inputs = fine_inputs(ws, cfg, device, seed)
        prepared, splats, pseudo = inputs.scene, inputs.splats, inputs.pseudo(cfg)
    else:
        ws = Workspace(Path(root) / "iteration")
        run_stage(
            "prepare",
            ws,
            resolve("prepare", cli={"views": views, "downscale": downscale}),
            StageEnv(device, seed, scene_dir=Path(scene)),
        )
        prepared = load_prepared(ws.output("prepare", "prepared"))
        splats, pseudo = initial_splats(prepared, cfg, seed), None
    total = cfg.iterations
    start = total // 2 if start is None else start
    cfg.iterations = start + window
    cfg.half_size_until = min(1.0, cfg.half_size_until * total / cfg.iterations)  # the phase ends where it would
    prof = profile(activities=[ProfilerActivity.CPU])
    marks: dict[str, float] = {}
    sizes: list[int] = []

    def on_step(it: int, params) -> None:
        if it == start:
            prof.start()
            marks["t0"] = time.perf_counter()
        elif it == start + window:
            marks["t1"] = time.perf_counter()
            prof.stop()
        if it > start:
            sizes.append(int(params["means"].shape[0]))

    torch.manual_seed(seed)
    train_gaussians(
        splats,
        prepared.train,
        cfg,
        device,
        extent=1.0,
        desc="bench iteration",
        seed=seed,
        has_masks=prepared.has_masks,
        on_step=on_step,
        pseudo=pseudo,
    )
    wall_ms = 1e3 * (marks["t1"] - marks["t0"]) / window
    totals: dict[str, float] = {}
    for ev in prof.key_averages():
        for name in (*PHASES, *(n for inner in INNER.values() for n in inner)):
            if ev.key == name or (not name.startswith("wgs:") and name in ev.key):
                totals[name] = max(totals.get(name, 0.0), ev.cpu_time_total / 1e3 / window)
    rows = {name: round(totals.get(name, 0.0), 3) for name in PHASES}
    rows["rest (Python, bookkeeping, profiler)"] = round(wall_ms - sum(rows.values()), 3)
    inner = {name: round(totals.get(name, 0.0), 3) for names in INNER.values() for name in names}
    img = prepared.train[0]
    return {
        "benchmark": "iteration",
        "stage": stage,
        "scene": workspace if stage == "fine" else scene,
        "size": [img.width, img.height],
        "views": len(prepared.train),
        "iterations": f"{start + 1}..{start + window} of {total}",
        "half_size_through": int(cfg.half_size_until * cfg.iterations),
        "gaussians": [min(sizes), max(sizes)],
        "ms_per_iteration_profiled": round(wall_ms, 3),
        "phases_ms": rows,
        "inside_ms": inner,
        "threads": torch.get_num_threads(),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }


def object_psnr(ws: Workspace, masks_from: Workspace) -> dict[str, float]:
    """PSNR of `ws`'s newest model against the photo inside the test masks of `masks_from`, per test
    view: the one number that compares a run with masks to one without (each renders its own
    background, which the mask leaves out)."""
    from wgs.gaussians.splats import load_checkpoint
    from wgs.gaussians.trainer import render_frame
    from wgs.metrics import psnr
    from wgs.stages.shared import background_for, newest_model

    scene = load_prepared(ws.output("prepare", "prepared"), load_test_images=True)
    masked = {f.name: f.object_pixels for f in load_prepared(masks_from.output("prepare", "prepared"), True).test}
    splats, _ = load_checkpoint(ws.output(newest_model(ws), "model"), scene.norm)
    out = {}
    for f in scene.test:
        keep = masked[f.name]
        rgb, _ = render_frame(splats, f, torch.device("cpu"), background_for(scene))
        out[f.name] = psnr(rgb[keep], f.pixels[keep])
    return out


def bench_masks(scene: str, root: str, preset: str, views: int, downscale: int) -> dict:
    """`wgs all` on photos without masks, with automatic masks (the default, which goes on without
    masks where the views disagree) and with none, both scored by PSNR inside the automatic test
    masks (`object_psnr`; masks made with `--mask-max-cut 1 --mask-max-missed 1`, kept whatever the
    vote and the training masks' hull say); wall
    times of each."""
    base = Path(root) / "masks"
    yardstick = Workspace(base / "scoring_masks")
    size = ("--views", str(views), "--downscale", str(downscale))
    wgs_cli(
        "-w",
        str(yardstick.root),
        "prepare",
        scene,
        *size,
        "--masks",
        "auto",
        "--mask-max-cut",
        "1",
        "--mask-max-missed",
        "1",
    )
    runs = {}
    for mode in ("auto", "none"):
        folder = base / mode
        t = wgs_cli("-w", str(folder), "all", scene, *size, "--masks", mode, "--preset", preset)
        runs[mode] = (Workspace(folder), t)
    out = {
        "benchmark": "masks",
        "scene": scene,
        "preset": preset,
        "views": views,
        "downscale": downscale,
        "metric": "PSNR (dB) inside the automatic test masks, each model on its own background",
        "masks": runs["auto"][0].finished("prepare")["summary"]["masks"],
    }
    for mode, (ws, t) in runs.items():
        per = object_psnr(ws, yardstick)
        out[mode] = {
            "object_psnr": statistics.fmean(per.values()),
            "per_view": per,
            "wgs_all_wall_s": round(t, 1),
            "eval_psnr": json.loads(ws.output("eval", "results").read_text())["psnr"],
        }
    out["gain_db"] = out["auto"]["object_psnr"] - out["none"]["object_psnr"]
    return out


def report(root: str, name: str, res: dict, shown: dict | None = None) -> None:
    """Write ROOT/NAME.json and print `shown` (default: all of it) as JSON."""
    Path(root).mkdir(parents=True, exist_ok=True)
    (Path(root) / f"{name}.json").write_text(json.dumps(res, indent=2))
    json.dump(res if shown is None else shown, sys.stdout, indent=2)
    print()


BENCHMARKS = ("rasterizer", "iteration", "pipeline", "batch", "contention", "knn", "sfm", "shape", "masks")
SHARED = Path(__file__).resolve().parents[2]  # the checkout's neighbours: benchmark data and fetched snapshots


@click.command()
@click.argument("which", type=click.Choice(BENCHMARKS))
@click.option("--json", "as_json", is_flag=True, help="rasterizer: print JSON instead of a table")
@click.option("--repeats", default=15, show_default=True, help="rasterizer: timed repeats of the fast path")
@click.option("--ref-repeats", default=3, show_default=True, help="rasterizer: timed repeats of the torch reference")
@click.option("--scene", default=str(SHARED / "shared" / "data" / "lego"), show_default=True, help="scene folder")
@click.option("--root", default="bench_out", show_default=True, help="folder of the runs and their JSON")
@click.option("--preset", default=None, help="default for pipeline, fast for batch")
@click.option("--views", default=4, show_default=True, help="training views")
@click.option("--downscale", default=2, show_default=True, help="image downscale")
@click.option("--prepared", default=None, help="contention: a workspace after `wgs prepare`")
@click.option("--stage", default="coarse", type=click.Choice(["coarse", "fine"]), help="iteration: whose training loop")
@click.option("--workspace", default=None, help="iteration --stage fine: a workspace after `wgs repair`")
@click.option(
    "--start",
    type=int,
    default=None,
    help="iteration: the profiled window's first iteration (default: the middle of the stage)",
)
@click.option("--iterations", default=300, show_default=True, help="contention: coarse iterations per run")
@click.option(
    "--variants", default=",".join(CONTENTION_VARIANTS), show_default=True, help="contention: thread settings"
)
@click.option("--matcher", default="auto", show_default=True, help="sfm: auto, exhaustive or sequential")
@click.option("--mirror", default=str(SHARED / ".mirror"), help="shape: folder of fetched snapshots (owner+name/repo)")
@click.option("--objects", default=",".join(SHAPE_OBJECTS), help="shape: held-out meshes by corpus name")
def main(which: str, as_json: bool, **options) -> None:
    """Benchmarks (not tests); each writes ROOT/WHICH.json where it says so."""
    a = SimpleNamespace(which=which, json=as_json, **options)
    if a.which == "iteration":
        if a.stage == "fine" and not (a.workspace and Workspace(Path(a.workspace)).output("repair", "views").is_file()):
            raise click.UsageError("iteration --stage fine needs --workspace WS where `wgs repair` has run")
        if a.stage == "coarse" and not Path(a.scene).is_dir():
            print(f"scene {a.scene} not found: skipped")
            return
        json.dump(
            bench_iteration(a.scene, a.root, a.views, a.downscale, stage=a.stage, workspace=a.workspace, start=a.start),
            sys.stdout,
            indent=2,
        )
        print()
        return
    if a.which == "masks":
        if not Path(a.scene).is_dir():
            print(f"scene {a.scene} not found: skipped")
            return
        res = bench_masks(a.scene, a.root, a.preset or "default", a.views, a.downscale)
        report(
            a.root,
            "masks",
            res,
            {k: v for k, v in res.items() if k not in ("auto", "none")}
            | {m: {k: v for k, v in res[m].items() if k != "per_view"} for m in ("auto", "none")},
        )
        return
    if a.which == "shape":
        report(a.root, "shape", bench_shape(a.mirror, a.root, tuple(a.objects.split(",")), a.preset or "fast", a.views))
        return
    if a.which == "sfm":
        if not Path(a.scene).is_dir():
            print(f"scene {a.scene} not found: skipped")
            return
        json.dump(bench_sfm(a.scene, a.root, a.matcher), sys.stdout, indent=2)
        print()
        return
    if a.which == "knn":
        json.dump(bench_knn(), sys.stdout, indent=2)
        print()
        return
    if a.which == "contention":
        if not a.prepared:
            raise click.UsageError("contention needs --prepared WORKSPACE")
        if not Workspace(a.prepared).stage_dir("prepare").is_dir():
            print(f"no prepared workspace at {a.prepared}: skipped")
            return
        res = bench_contention(a.prepared, a.root, a.iterations, tuple(a.variants.split(",")))
        json.dump(res, sys.stdout, indent=2)
        print()
        return
    if a.which == "batch":
        report(a.root, "batch", bench_batch(a.root, a.preset or "fast"))
        return
    if a.which == "pipeline":
        if not Path(a.scene).is_dir():
            print(f"scene {a.scene} not found: skipped")
            return
        report(a.root, "pipeline", bench_pipeline(a.scene, a.root, a.preset or "default", a.views, a.downscale))
        return
    res = bench_rasterizer(a.repeats, a.ref_repeats)
    if a.json:
        json.dump(res, sys.stdout, indent=2)
        print()
        return
    print(f"{'case':>14} {'backend':>10} {'fwd median':>11} {'fwd+bwd median':>15} {'(min..max)':>18}")
    for r in res["cases"]:
        for be in ("numba", "torch_reference"):
            f, b = r[be]["forward"], r[be]["forward_backward"]
            print(
                f"{r['size']}px x {r['gaussians']:>6} {be:>10} {f['median_s']:>10.4f}s {b['median_s']:>14.4f}s"
                f"  ({b['min_s']:.4f}..{b['max_s']:.4f})"
            )
        print(f"{'':>14} speed-up (fwd+bwd): {r['speedup_forward_backward']:.1f}x")
    print(f"peak memory: {res['peak_memory_mb']:.0f} MiB")


if __name__ == "__main__":
    main()
