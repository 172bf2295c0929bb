"""A calibration made while another process keeps the cores busy, then the next run's on an idle
machine: the cached one is made again (`estimate.cached_calibration`, `BUSIER_RATIO`).

A 2-thread matrix-product loop (1500x1500) stands for another run's processes. Printed: the busy
and the idle calibration's probe, a training view at 200x200 px and D's step, and what the third
call costs where the cache is kept.

    python tools/experiments/xp_busy_calibration.py
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script from anywhere
os.environ["WGS_CACHE"] = tempfile.mkdtemp(prefix="wgs-busy-calibration-")  # not the user's cache
from wgs.estimate import cache_dir, cached_calibration  # noqa: E402

LOAD = "import torch\ntorch.set_num_threads(2)\na = torch.randn(1500, 1500)\nwhile True:\n    a @ a"


def probe_made() -> float:
    """The newest held calibration's probe."""
    return next(iter(json.loads((cache_dir() / "calibration.json").read_text()).values()))[-1]["probe_s"]


def main() -> None:
    cpu = torch.device("cpu")
    load = subprocess.Popen([sys.executable, "-c", LOAD])
    time.sleep(3)
    busy = cached_calibration(cpu)
    busy_probe = probe_made()
    load.kill()
    load.wait()
    time.sleep(1)
    t = time.perf_counter()
    idle = cached_calibration(cpu)
    second_s = time.perf_counter() - t
    for name, cal, probe in (("busy", busy, busy_probe), ("idle", idle, probe_made())):
        print(
            f"{name}: probe {probe * 1e3:.1f} ms, a view at 200 px {cal.view_s(200 * 200) * 1e3:.1f} ms, "
            f"D step {cal.d_step_s * 1e3:.0f} ms"
        )
    t = time.perf_counter()
    kept = cached_calibration(cpu) == idle
    print(f"second call {second_s:.1f} s; third call {time.perf_counter() - t:.2f} s (cache kept: {kept})")


if __name__ == "__main__":
    main()
