"""`wgs ablate`: the paper's comparison (Table 2) on one scene, in one command.

Rows share every stage whose inputs are identical: one prepare and one coarse per repeat, one
mask-data run per masking strategy (its pairs hold both LL and RGB, so every domain reuses them).
A row's time is the sum of the wall times of the stages its method needs, shared ones included.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import shutil
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError
from .io import atomic_write_bytes, atomic_write_json, read_json
from .progress import fmt, log
from .stages.registry import METHOD, REGISTRY, stages_through
from .stages.shared import plain_3dgs_config
from .workspace import STAGE_DIRS, Workspace


@dataclass(frozen=True)
class Row:
    name: str
    strategy: str | None  # None: plain 3DGS, no repair
    domain: str = "wavelet"
    use_u: bool = False
    levels: int = 1
    prior: str = "none"  # the paper's rows train D from scratch; the prior row starts from the shipped prior
    carve: bool = False  # V and S carve the hull (not in the paper; the product's default)
    own_shape: bool = False  # the hull shrunk by what the photos' masks allow (shape.own_shape; the product's default)
    label: dict[str, bool] = field(default_factory=dict)

    def overrides(self) -> dict[str, dict[str, Any]]:
        """The row's settings, per config table."""
        return {
            "mask_data": {"strategy": self.strategy},
            "finetune": {"domain": self.domain, "use_u": self.use_u, "levels": self.levels, "prior": self.prior},
            "repair": {"carve": self.carve, "shape_revolution": self.own_shape, "shape_smooth": self.own_shape},
        }


ROWS: dict[str, Row] = {
    r.name: r
    for r in (
        Row("loo-rgb", "loo", "rgb"),
        Row("offline-rgb", "offline-rm", "rgb"),
        Row("orm-rgb", "orm", "rgb"),
        Row("orm-wavelet", "orm", "wavelet"),
        Row("orm-wavelet-u", "orm", "wavelet", use_u=True),
        Row("orm-wavelet-u-prior", "orm", "wavelet", use_u=True, prior="builtin"),
        Row("orm-wavelet-u-prior-carve", "orm", "wavelet", use_u=True, prior="builtin", carve=True),
        Row(
            "orm-wavelet-u-prior-carve-shape", "orm", "wavelet", use_u=True, prior="builtin", carve=True, own_shape=True
        ),
        Row("3dgs", None),
        Row("orm-wavelet-u-j2", "orm", "wavelet", use_u=True, levels=2),
    )
}
PAPER_ROWS = (
    "loo-rgb",
    "offline-rgb",
    "orm-rgb",
    "orm-wavelet",
    "orm-wavelet-u",
    "orm-wavelet-u-prior",
    "orm-wavelet-u-prior-carve",
    "orm-wavelet-u-prior-carve-shape",
    "3dgs",
)
TIME_OF = "orm-wavelet-u-prior"  # plain 3DGS gets the time of the full method (wgs all's default)
# a row's own stages (what runs only on request, the plain-3DGS baseline, is its own row)
AFTER_PAIRS = tuple(s.name for s in REGISTRY if s.name not in stages_through("mask_data") and not s.on_request)


def parse_rows(spec: str) -> list[Row]:
    presets = {"paper": list(PAPER_ROWS), "all": list(ROWS)}
    names = presets.get(spec, [s.strip() for s in spec.split(",") if s.strip()])
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        raise InputError(f"unknown ablation row(s) {', '.join(unknown)} (known: {', '.join(ROWS)})")
    if "3dgs" in names:  # the baseline's time budget comes from TIME_OF: run it first
        names = [n for n in names if n != "3dgs"] + ([] if TIME_OF in names else [TIME_OF]) + ["3dgs"]
    return [ROWS[n] for n in names]


def copy_stages(src: Workspace, dst: Workspace, stages: tuple[str, ...]) -> None:
    """Give `dst` the finished stages of `src` (their manifests keep them fresh there)."""
    dst.root.mkdir(parents=True, exist_ok=True)
    for st in stages:
        s, d = src.stage_dir(st), dst.stage_dir(st)
        if src.manifest(st) is None:
            raise InputError(f"shared stage {st} is missing", s)
        if d.exists() and (dst.manifest(st) or {}).get("fingerprint") == src.finished(st)["fingerprint"]:
            continue
        shutil.rmtree(d, ignore_errors=True)
        shutil.copytree(s, d)


def row_times(ws: Workspace) -> dict[str, float]:
    return {st: (ws.manifest(st) or {}).get("wall_time_s", 0.0) for st in METHOD if ws.manifest(st)}


def run_ablation(
    ctx,
    scene_dir: Path,
    root: Path,
    rows: list[Row],
    repeats: int,
    preset: str | None,
    prepare_overrides: dict[str, Any],
) -> list[dict[str, Any]]:
    from .estimate import RunTiming
    from .stages.registry import run_stage

    device = ctx.torch_device()
    # the working size chosen for the machine where the options do not set it (one prepare for every row)
    working_size = RunTiming(device, ctx.configs(preset))
    records: list[dict[str, Any]] = []
    for rep in range(repeats):
        seed = ctx.seed + rep
        base = root / f"repeat{rep}" if repeats > 1 else root
        env = ctx.env(device, seed=seed, scene_dir=scene_dir, working_size=working_size)

        def workspace(name: str, base: Path = base) -> Workspace:
            return Workspace(base / name, resume=ctx.resume, checkpoint_every=ctx.checkpoint_every)

        def run(ws: Workspace, stages: tuple[str, ...], overrides: dict[str, dict[str, Any]], env=env) -> None:
            for name in stages:
                run_stage(name, ws, ctx.config(name, preset, **overrides.get(name, {})), env)

        shared = workspace("_shared")
        run(shared, stages_through("coarse"), {"prepare": prepare_overrides})
        masks: dict[str, Workspace] = {}
        timings: dict[str, dict[str, float]] = {}
        for row in rows:
            ws = workspace(row.name)
            log(f"ablate: row {row.name} (repeat {rep + 1}/{repeats})")
            if row.strategy is None:
                copy_stages(shared, ws, ("prepare",))
                budget = sum(t for st, t in timings[TIME_OF].items() if st != "prepare")
                coarse_s = shared.finished("coarse")["train_seconds"]
                cfg = plain_3dgs_config(
                    ctx.config("coarse", preset), budget, coarse_s, ctx.config("baseline", preset).headroom
                )
                run_stage("coarse", ws, cfg, env)
                run(ws, ("eval",), {}, dataclasses.replace(env, final="coarse"))
                timings[row.name] = {
                    "prepare": ws.finished("prepare")["wall_time_s"],
                    "coarse": ws.finished("coarse")["wall_time_s"],
                }
            else:
                if row.strategy not in masks:
                    mws = workspace(f"_mask_{row.strategy}")
                    copy_stages(shared, mws, stages_through("coarse"))
                    run(mws, ("mask_data",), row.overrides())
                    masks[row.strategy] = mws
                copy_stages(masks[row.strategy], ws, stages_through("mask_data"))
                run(ws, AFTER_PAIRS, row.overrides())
                timings[row.name] = row_times(ws)
            res = read_json(ws.output("eval", "results"))
            records.append(
                {
                    "row": row.name,
                    "repeat": rep,
                    "seed": seed,
                    "psnr": res["psnr"],
                    "ssim": res["ssim"],
                    "lpips": res["lpips"],
                    "repair_gain_db": (res.get("repair_gain") or {}).get("gain_db"),
                    # U trained but left out where it did not beat no HF repair on held-out crops
                    "u_used": (ws.manifest("finetune") or {}).get("u_used") if row.use_u else None,
                    "time_s": round(sum(timings[row.name].values()), 2),
                    "stage_times_s": timings[row.name],
                }
            )
    return records


def aggregate(records: list[dict[str, Any]], rows: list[Row]) -> list[dict[str, Any]]:
    out = []
    for row in rows:
        rs = [r for r in records if r["row"] == row.name]
        repair = row.strategy is not None
        agg: dict[str, Any] = {
            "row": row.name,
            "strategy": row.strategy,
            "domain": row.domain if repair else None,
            "use_u": row.use_u,
            "levels": row.levels if repair else None,
            "prior": row.prior if repair else None,
            "repeats": len(rs),
            "u_kept": sum(bool(r.get("u_used")) for r in rs) if row.use_u and repair else None,
        }
        for k in ("psnr", "ssim", "lpips", "time_s", "repair_gain_db"):
            vals = [r[k] for r in rs if r.get(k) is not None]
            agg[k] = statistics.fmean(vals) if vals else None
            agg[f"{k}_std"] = statistics.pstdev(vals) if len(vals) > 1 else (0.0 if vals else None)
        stages = sorted({s for r in rs for s in r["stage_times_s"]}, key=list(STAGE_DIRS).index)
        agg["stage_times_s"] = {s: statistics.fmean(r["stage_times_s"].get(s, 0.0) for r in rs) for s in stages}
        out.append(agg)
    return out


def u_note(r: dict[str, Any]) -> str:
    """How often a requested U was kept (finetune leaves it out where it does not beat no HF repair)."""
    kept = r.get("u_kept")
    return "" if kept is None or kept == r["repeats"] else f" (kept {kept}/{r['repeats']})"


def pareto(rows: list[dict[str, Any]]) -> set[str]:
    """Rows no other row beats in both time (lower) and PSNR (higher)."""
    front = set()
    for a in rows:
        if a["psnr"] is None:
            continue
        dominated = any(
            b is not a
            and b["psnr"] is not None
            and b["time_s"] <= a["time_s"]
            and b["psnr"] >= a["psnr"]
            and (b["time_s"] < a["time_s"] or b["psnr"] > a["psnr"])
            for b in rows
        )
        if not dominated:
            front.add(a["row"])
    return front


def write_outputs(root: Path, agg: list[dict[str, Any]], records: list[dict[str, Any]]) -> None:
    def pm(r, k, nd):
        return fmt(r[k], nd) + (f" ± {fmt(r[k + '_std'], nd)}" if r["repeats"] > 1 and r[k] is not None else "")

    tick = {True: "✓", False: ""}
    stages = [s for s in STAGE_DIRS if s != "eval" and any(s in r["stage_times_s"] for r in agg)]
    lines = [
        "# wgs ablation (Table 2 of WaveletGaussian)",
        "",
        "| row | LOO | offline RM | online RM | wavelet D | U | prior | PSNR | SSIM | LPIPS | repair gain (dB) | "
        "time (s) | " + " | ".join(f"{s} (s)" for s in stages) + " |",
        "| --- | :-: | :-: | :-: | :-: | :-: | :-: | ---: | ---: | ---: | ---: | ---: | "
        + " | ".join("---:" for _ in stages)
        + " |",
    ]
    for r in agg:
        st = r["strategy"]
        cells = [
            tick[st == "loo"],
            tick[st == "offline-rm"],
            tick[st == "orm"],
            tick[r["domain"] == "wavelet"] + (f" J={r['levels']}" if (r["levels"] or 1) > 1 else ""),
            tick[bool(r["use_u"]) and st is not None] + u_note(r),
            tick[r.get("prior") not in (None, "none")],
        ]
        lines.append(
            f"| {r['row']} | " + " | ".join(cells) + f" | {pm(r, 'psnr', 2)} | {pm(r, 'ssim', 3)} | "
            f"{pm(r, 'lpips', 3)} | {pm(r, 'repair_gain_db', 2)} | {pm(r, 'time_s', 1)} | "
            + " | ".join(fmt(r["stage_times_s"].get(s), 1) for s in stages)
            + " |"
        )
    by = {r["row"]: r for r in agg}
    if "loo-rgb" in by and "orm-wavelet-u" in by:
        a, b = by["orm-wavelet-u"], by["loo-rgb"]
        lines += [
            "",
            f"time(orm-wavelet-u) / time(loo-rgb) = {a['time_s'] / b['time_s']:.2f}; "
            f"PSNR difference {a['psnr'] - b['psnr']:+.2f} dB",
        ]
    for name in ("orm-wavelet-u", "3dgs"):
        if "orm-wavelet-u-prior" in by and name in by:
            a, b = by["orm-wavelet-u-prior"], by[name]
            lines += [
                "",
                f"PSNR(orm-wavelet-u-prior) - PSNR({name}) = {a['psnr'] - b['psnr']:+.2f} dB "
                f"(times {a['time_s']:.0f} s and {b['time_s']:.0f} s)",
            ]
    atomic_write_bytes(root / "ablation.md", ("\n".join(lines) + "\n").encode())
    buf = io.StringIO()
    cols = [
        "row",
        "strategy",
        "domain",
        "use_u",
        "levels",
        "prior",
        "repeats",
        "psnr",
        "psnr_std",
        "ssim",
        "ssim_std",
        "lpips",
        "lpips_std",
        "repair_gain_db",
        "repair_gain_db_std",
        "time_s",
        "time_s_std",
    ]
    w = csv.writer(buf)
    w.writerow(cols + [f"{s}_s" for s in stages])
    for r in agg:
        w.writerow([r.get(c) for c in cols] + [r["stage_times_s"].get(s) for s in stages])
    atomic_write_bytes(root / "ablation.csv", buf.getvalue().encode())
    atomic_write_json(root / "ablation.json", {"rows": agg, "runs": records})
    plot(root / "ablation.png", agg)


def plot(path: Path, agg: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    front = pareto(agg)
    has_lpips = any(r["lpips"] is not None for r in agg)
    fig, axes = plt.subplots(1, 2 if has_lpips else 1, figsize=(10 if has_lpips else 5.5, 3.6), squeeze=False)
    for ax, key, better in zip(axes[0], ("psnr", "lpips"), ("higher", "lower"), strict=False):
        pts = [r for r in agg if r[key] is not None]
        for r in pts:
            ax.errorbar(
                r["time_s"],
                r[key],
                xerr=r["time_s_std"] or 0,
                yerr=r[f"{key}_std"] or 0,
                fmt="o",
                color="tab:red" if r["row"] in front else "tab:blue",
            )
            ax.annotate(r["row"], (r["time_s"], r[key]), textcoords="offset points", xytext=(4, 4), fontsize=7)
        fr = sorted((r for r in pts if r["row"] in front), key=lambda r: r["time_s"])
        if key == "psnr" and fr:
            ax.plot([r["time_s"] for r in fr], [r["psnr"] for r in fr], "--", color="tab:red", label="Pareto front")
            ax.legend(fontsize=7)
        ax.set(xlabel="total time (s)", ylabel=f"{key.upper()} ({better} is better)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
