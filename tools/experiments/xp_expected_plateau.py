"""The estimate made before training against the time the stages took, for finished `wgs all`
workspaces, as a function of where the coarse pilots are expected to stop gaining.

Two ways to expect it, each fitted on the workspaces in `--fit` (the least worst error over them),
the others being the held-out check:
- one plateau for every scene (as `wgs.cost.EXPECTED_PLATEAU` was), with a common scale of the
  training loops' factors (`FACTOR` in the coarse, mask-data and fine stages' settings);
- the line from the hull's leave-one-out silhouette IoU (`wgs.cost.plateau_from_hull`), over a grid
  of its two IoU anchors (`HULL_PLATEAU_LINE`).

    python xp_expected_plateau.py --fit WS... [--plateaus 300 400 ...] [--scales 1.0 1.1 ...] WORKSPACE...
"""

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path

import xp_estimate

import wgs.cost
import wgs.stages.coarse.settings as coarse
import wgs.stages.fine.settings as fine
import wgs.stages.mask_data.settings as mask_data
from wgs.estimate import hull_loo_iou
from wgs.workspace import Workspace

LOOPS = (coarse, mask_data, fine)  # the stages whose FACTOR scales a training loop
# the factors the scales multiply: those before the fit that set the plateau from the hull (which
# then scaled them by 1.15, a scale of 1.15 here)
SHIPPED = {coarse: 1.0, mask_data: 0.8, fine: 0.93}
SHIPPED_LINE = wgs.cost.HULL_PLATEAU_LINE
ANCHORS_LOW, ANCHORS_HIGH = (0.72, 0.74, 0.76, 0.78, 0.80), (0.84, 0.86, 0.88, 0.90, 0.92, 0.94)


def ratio(ws: Workspace, expect: Callable[[float | None], int], scale: float) -> float:
    """Before training: the modelled stages over what they took, the plateau expected by `expect`."""
    xp_estimate.plateau_from_hull = expect
    for m in LOOPS:
        m.FACTOR = SHIPPED[m] * scale
    row = xp_estimate.one(ws, None)
    return row["after_prepare"]["now"] / row["after_prepare"]["actual"]


def worst(ratios: list[float]) -> float:
    return math.exp(max(abs(math.log(r)) for r in ratios))


def line(low: float, high: float) -> Callable[[float | None], int]:
    (_, early), (_, late) = SHIPPED_LINE

    def expect(loo_iou: float | None) -> int:
        wgs.cost.HULL_PLATEAU_LINE = ((low, early), (high, late))
        return wgs.cost.plateau_from_hull(loo_iou)

    return expect


def table(grid: dict, names: list[str], fit: set[str], heads: tuple[str, ...]) -> tuple:
    print("| " + " | ".join(heads) + " | " + " | ".join(names) + " | worst, fit | worst, held out |")
    print("|" + " ---: |" * (len(heads) + len(names) + 2))
    for key, row in grid.items():
        held = [row[n] for n in names if n not in fit]
        print(
            "| "
            + " | ".join(f"{k:g}" for k in key)
            + " | "
            + " | ".join(f"{row[n]:.2f}" for n in names)
            + f" | {worst([row[n] for n in fit]):.2f} | {worst(held) if held else 0:.2f} |"
        )
    # the least worst error, then the least mean error (the worst is often one scene's, whatever the key)
    best = min(
        grid,
        key=lambda k: (round(worst([grid[k][n] for n in fit]), 2), sum(abs(math.log(grid[k][n])) for n in fit)),
    )
    print(f"\nchosen on {', '.join(sorted(fit))}: {', '.join(f'{h} {k:g}' for h, k in zip(heads, best, strict=True))}")
    for n in names:
        print(f"  {n}{' (fit)' if n in fit else ''}: {grid[best][n]:.2f}")
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("workspaces", nargs="+", type=Path)
    ap.add_argument("--fit", nargs="+", type=Path, required=True)
    ap.add_argument("--plateaus", nargs="+", type=int, default=[250, 300, 350, 400, 450, 500, 550, 625])
    ap.add_argument("--scales", nargs="+", type=float, default=[1.0, 1.05, 1.1, 1.15, 1.2, 1.25])
    a = ap.parse_args()
    paths = list(dict.fromkeys([*a.fit, *a.workspaces]))
    names = [p.name for p in paths]
    fit = {p.name for p in a.fit}
    print(
        "| workspace | hull's leave-one-out IoU | pilots' plateau | expected from the hull |\n"
        "| --- | ---: | ---: | ---: |"
    )
    for n, p in zip(names, paths, strict=True):
        ws = Workspace(p)
        iou = hull_loo_iou(json.loads((ws.stage_dir("prepare") / "scene.json").read_text()))
        found = ((ws.manifest("coarse") or {}).get("stopping") or {}).get("plateau")
        print(f"| {n} | {iou} | {found} | {line(*(x for x, _ in SHIPPED_LINE))(iou)} |")
    print("\nOne plateau for every scene:\n")
    one = {
        (p, s): {n: ratio(Workspace(w), lambda _iou, p=p: p, s) for n, w in zip(names, paths, strict=True)}
        for p in a.plateaus
        for s in a.scales
    }
    table(one, names, fit, ("expected plateau", "scale"))
    print("\nThe line from the hull's leave-one-out IoU (its anchors' IoUs), at the factors before the fit:\n")
    lines = {
        (lo, hi): {n: ratio(Workspace(w), line(lo, hi), 1.0) for n, w in zip(names, paths, strict=True)}
        for lo in ANCHORS_LOW
        for hi in ANCHORS_HIGH
    }
    lo, hi = table(lines, names, fit, ("low IoU", "high IoU"))
    print(f"\nThen a common scale, with that line ({lo:g}, {hi:g}):\n")
    scaled = {
        (s,): {n: ratio(Workspace(w), line(lo, hi), s) for n, w in zip(names, paths, strict=True)} for s in a.scales
    }
    table(scaled, names, fit, ("scale",))
    wgs.cost.HULL_PLATEAU_LINE = SHIPPED_LINE


if __name__ == "__main__":
    main()
