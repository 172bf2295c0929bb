"""The coarse stage's pilots against their model, beside the rest of the run against the estimate
printed once they ended: would the pilots' own speed correct that estimate?

For each finished `wgs all` workspace: the pilots' wall time over their modelled time (each round of
side-by-side pilots as long as its longest, at the iterations they ran, from the run's recorded
calibration), and the rest's (the coarse models, then the later stages) time over its estimate
with the pilots' plateau, as `xp_estimate.py` computes it.

    python xp_pilot_speed.py WORKSPACE...
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import xp_estimate  # noqa: E402

from wgs.cost import Calibration, side_by_side_share  # noqa: E402
from wgs.stages.coarse.settings import FACTOR  # noqa: E402
from wgs.stages.shared import recorded_config  # noqa: E402
from wgs.threads import side_by_side  # noqa: E402
from wgs.workspace import Workspace  # noqa: E402


def pilots_over_model(ws: Workspace) -> float:
    run = ws.run_record()
    cal = Calibration(**{**run["calibration"], "raster": tuple(run["calibration"]["raster"])})
    cfg, scene = recorded_config(ws, "coarse"), run["scene"]
    stopping = (ws.manifest("coarse") or {})["stopping"]
    ends = list(stopping["pilot_iterations"].values())
    pixels = scene["width"] * scene["height"]
    workers = side_by_side(len(ends), cfg.iterations, pixels // 4, cal.device.startswith("cpu"))
    rounds = [max(ends[i : i + workers]) for i in range(0, len(ends), workers)]
    return stopping["pilots_s"] / (sum(rounds) * cal.view_s(pixels / 4) * side_by_side_share(workers) * FACTOR)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("workspaces", nargs="+", type=Path)
    a = ap.parse_args()
    print("| workspace | pilots took / modelled | the rest took / its estimate after the pilots |")
    print("| --- | ---: | ---: |")
    for p in a.workspaces:
        ws = Workspace(p)
        rest = xp_estimate.one(ws, None)["after_pilots"]
        print(f"| {p.name} | {pilots_over_model(ws):.2f} | {rest['took'] / rest['modelled']:.2f} |")


if __name__ == "__main__":
    main()
