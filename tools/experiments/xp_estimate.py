"""The run-time estimate against the time each stage took, for finished `wgs all` workspaces, and
for those run with a budget, the time against the budget and the quality it bought.

For each workspace: the estimate its run printed (`run.json`), the estimate the model in
`wgs/estimate.py` gives now from the same calibration and the stages' recorded settings, and
each stage's wall time (its manifest); with TIMES (lines `NAME rc=0 wall=SECONDS`, as a run
queue writes them) also the whole command's wall time. And once the coarse stage's pilots ended,
the model's estimate of the rest (the coarse models, then the stages after them) with the plateau
the pilots found (`RunTiming.after_pilots`, which `wgs all` prints then; where the run recorded
it, the one printed) against the time they took (the coarse stage's less its pilots').
With `--calibration-of WS` (repeated) the model times the machine by the median of those
workspaces' recorded calibrations (`estimate.typical`, as `wgs` does with its day's
calibrations) in place of each run's own.

    python xp_estimate.py [--times TIMES] [--calibration-of WS ...] WORKSPACE...
"""

import argparse
import dataclasses
import json
from pathlib import Path

from wgs.cost import FIT_MASK_SHARE, Calibration, SceneFacts, plateau_from_hull
from wgs.estimate import TRAIN_STAGES, hull_loo_iou, stage_seconds, typical
from wgs.io.images import find_with_stem, read_image, to_mask
from wgs.scene.prepare import mask_share
from wgs.stages.registry import REGISTRY
from wgs.stages.shared import recorded_config
from wgs.workspace import Workspace

LOSS_2_CORES = (0.0005, 2.0e-7)  # s, s per pixel: the photometric loss, forward + backward (2026-11-27)
TABLES = [s.name for s in REGISTRY]


def share(ws: Workspace) -> float:
    """The training photos' mask share, as prepare records it (read from the masks where a
    workspace was prepared before it was recorded)."""
    info = json.loads((ws.stage_dir("prepare") / "scene.json").read_text())
    if "training_share" in info["masks"]:
        return info["masks"]["training_share"]
    folder = ws.stage_dir("prepare") / "masks"
    found = [find_with_stem(folder, Path(n).stem) for n in info["train_names"]]
    if not all(found):
        return FIT_MASK_SHARE
    return mask_share([to_mask(read_image(p)) for p in found if p is not None])


def recorded_calibration(ws: Workspace) -> Calibration:
    """The calibration `ws`'s run recorded."""
    cal = ws.run_record()["calibration"]
    if "raster_all" in cal:  # a calibration of the rasterizer alone: the loss's time added (2-core CPU, quiet)
        loss = LOSS_2_CORES
        cal = {
            **{k: v for k, v in cal.items() if k not in ("raster_all", "raster_one")},
            "raster": (cal["raster_all"][0] + loss[0], cal["raster_all"][1] + loss[1]),
        }
    return Calibration(**{**cal, "raster": tuple(cal["raster"])})


def one(ws: Workspace, wall: float | None, cal: Calibration | None = None) -> dict:
    """`ws`'s run timed against the model, with `cal` in place of its own calibration if given."""
    run = ws.run_record()
    cal = cal or recorded_calibration(ws)
    sc = run["scene"]
    cfgs = {t: recorded_config(ws, t) for t in TABLES}
    masks = sc.get("has_masks", (ws.manifest("prepare") or {}).get("summary", {}).get("has_masks", True))
    info = json.loads((ws.stage_dir("prepare") / "scene.json").read_text())
    facts = SceneFacts(
        sc["width"],
        sc["height"],
        sc["train"],
        sc["test"],
        has_masks=masks,
        mask_share=share(ws),
        expected_plateau=plateau_from_hull(hull_loo_iou(info)),
    )
    now = stage_seconds(cal, cfgs, facts)
    stopping = (ws.manifest("coarse") or {}).get("stopping")
    found = None
    if stopping:
        ends = tuple(stopping["pilot_iterations"].values())
        ran = dataclasses.replace(facts, plateau=stopping["plateau"], pilot_ends=ends)
        found = stage_seconds(cal, cfgs, ran)
    actual = {t: (ws.manifest(t) or {}).get("wall_time_s") for t in TABLES}
    printed = run.get("estimate") or {}
    shown = [t for t in TABLES if t != "prepare" and printed.get(t) is not None and actual[t] is not None]
    tot = {k: sum(d[t] for t in shown) for k, d in (("printed", printed), ("now", now), ("actual", actual))}
    res = ws.output("eval", "results")
    quality = {}
    if res.is_file():
        r = json.loads(res.read_text())
        quality = {"gc": r["coarse"]["psnr"], "gf": r["psnr"], "iou": r.get("silhouette_iou")}
    # the rest after the first training stage, as printed and as it would be rescaled by that
    # stage's own ratio (tried and not kept: docs/what-we-tried.md, "Speed")
    first = next((t for t in shown if t in TRAIN_STAGES), None)
    rest = shown[shown.index(first) + 1 :] if first else []
    after_first = None
    if rest:
        took = sum(actual[t] for t in rest)
        ratio = actual[first] / printed[first]
        after_first = {
            "stage": first,
            "printed_over_took": sum(printed[t] for t in rest) / took,
            "rescaled_over_took": ratio * sum(printed[t] for t in rest) / took,
        }
    after_pilots = None
    if found is not None and "coarse" in shown and "pilots_s" in stopping:
        later = shown[shown.index("coarse") :]
        recorded = run.get("estimate_after_pilots") or {}
        after_pilots = {
            "plateau": stopping["plateau"],
            "stages": later,
            "modelled": sum(found[t] for t in later),
            "printed": sum(recorded[t] for t in later) if all(t in recorded for t in later) else None,
            "took": sum(actual[t] for t in later) - stopping["pilots_s"],
            "pilots_s": stopping["pilots_s"],
        }
    return {
        "after_pilots": after_pilots,
        "after_first": after_first,
        "quality": quality,
        "workspace": ws.root.name,
        "size": f"{sc['width']}x{sc['height']}",
        "mask_share": share(ws),
        "budget_s": run.get("budget_s"),
        "stages": {t: {"printed": printed.get(t), "now": now[t], "actual": actual[t]} for t in shown},
        "after_prepare": tot,
        "prepare_s": actual["prepare"],
        "wall_s": wall,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--times", type=Path)
    ap.add_argument("--calibration-of", type=Path, action="append", default=[])
    a = ap.parse_args()
    cal = typical([recorded_calibration(Workspace(p)) for p in a.calibration_of]) if a.calibration_of else None
    walls = {}
    if a.times and a.times.is_file():
        for line in a.times.read_text().splitlines():
            name, _, wall = line.split()
            walls[name] = float(wall.split("=")[1])
    rows = [one(Workspace(p), walls.get(p.name), cal) for p in a.workspaces]
    print(
        "| workspace | size | budget (s) | estimate printed (s) | model now (s) | the stages took (s) | "
        "printed / took | now / took | prepare (s) | `wgs all` wall (s) | (prepare + printed) / wall |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        t, wall = r["after_prepare"], r["wall_s"]
        whole = f"{(r['prepare_s'] + t['printed']) / wall:.2f}" if wall else ""
        print(
            f"| {r['workspace']} | {r['size']} | {r['budget_s'] or ''} | {t['printed']:.0f} | {t['now']:.0f} | "
            f"{t['actual']:.0f} | {t['printed'] / t['actual']:.2f} | {t['now'] / t['actual']:.2f} | "
            f"{r['prepare_s']:.0f} | "
            f"{f'{wall:.0f}' if wall else ''} | {whole} |"
        )
    budgeted = [r for r in rows if r["budget_s"] and r["wall_s"]]
    if budgeted:
        print(
            "\n| workspace | budget (min) | working size | `wgs all` wall (s) | wall / budget | G_c -> G_f PSNR (dB) "
            "| G_f silhouette IoU |"
        )
        print("| --- | ---: | --- | ---: | ---: | ---: | ---: |")
        for r in budgeted:
            q = r["quality"]
            print(
                f"| {r['workspace']} | {r['budget_s'] / 60:.0f} | {r['size']} | {r['wall_s']:.0f} | "
                f"{r['wall_s'] / r['budget_s']:.2f} | {q.get('gc', 0):.2f} -> {q.get('gf', 0):.2f} | "
                f"{q.get('iou') or 0:.3f} |"
            )
    print("\n| workspace | the rest after | printed / took | rescaled / took |\n| --- | --- | ---: | ---: |")
    for r in rows:
        if (a := r["after_first"]) is not None:
            print(f"| {r['workspace']} | {a['stage']} | {a['printed_over_took']:.2f} | {a['rescaled_over_took']:.2f} |")
    print(
        "\n| workspace | pilots' plateau | pilots (s) | the rest once they ended: printed / model now (s) | took (s) "
        "| printed / took | now / took |\n| --- | ---: | ---: | ---: | ---: | ---: | ---: |"
    )
    for r in rows:
        if (c := r["after_pilots"]) is not None:
            printed, took = c["printed"], c["took"]
            shown_s, ratio = ("", "") if printed is None else (f"{printed:.0f}", f"{printed / took:.2f}")
            print(
                f"| {r['workspace']} | {c['plateau']} | {c['pilots_s']:.0f} | {shown_s} / {c['modelled']:.0f} | "
                f"{took:.0f} | {ratio} | {c['modelled'] / took:.2f} |"
            )
    print()
    for r in rows:
        stages = r["stages"].items()
        print(
            r["workspace"],
            f"mask share {r['mask_share']:.3f}",
            "printed/now/took:",
            " ".join(f"{k} {v['printed']}/{v['now']}/{v['actual']:.1f}" for k, v in stages),
        )


if __name__ == "__main__":
    main()
