"""Benchmarks (not tests): `python -m wgs.bench rasterizer [--json] [--repeats R]`.

The rasterizer benchmark times our numba fast path and the pure-torch reference in the same run
on random scenes with realistic footprints (a few px to tens of px), forward and forward+backward,
median and spread over repeats, plus peak memory (RSS) of the process.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import torch

from .gaussians.render import rasterize
from .workspace import peak_memory_mb

CASES = ((128, 10_000), (256, 50_000))


def random_scene(n: int, size: int, seed: int = 0, dtype=torch.float32):
    """n Gaussians in a ball seen by one camera at distance 2.5 (footprints ~2-30 px)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.5 - 4.0)
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[2, 3] = 2.5
    f = size * 1.2
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opac, colors, viewmat, K


def time_backend(backend: str, size: int, n: int, repeats: int) -> dict:
    scene = random_scene(n, size)
    weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))
    fwd, both = [], []
    for i in range(repeats + 1):  # the first run warms up (numba loads its cache)
        params = [t.detach().clone().requires_grad_(True) for t in scene[:5]]
        t0 = time.perf_counter()
        rgb, alpha, _ = rasterize(*params, scene[5], scene[6], size, size, backend=backend)
        t1 = time.perf_counter()
        ((rgb * weights).sum() + alpha.sum()).backward()
        t2 = time.perf_counter()
        if i:
            fwd.append(t1 - t0)
            both.append(t2 - t0)

    def stats(xs):
        return {"median_s": statistics.median(xs), "min_s": min(xs), "max_s": max(xs)}

    return {"forward": stats(fwd), "forward_backward": stats(both), "repeats": repeats}


def bench_rasterizer(repeats: int, ref_repeats: int) -> dict:
    rows = []
    for size, n in CASES:
        fast = time_backend("numba", size, n, repeats)
        ref = time_backend("torch", size, n, ref_repeats)
        rows.append({
            "size": size, "gaussians": n, "numba": fast, "torch_reference": ref,
            "speedup_forward_backward": ref["forward_backward"]["median_s"] / fast["forward_backward"]["median_s"],
        })
    return {"benchmark": "rasterizer", "machine": {"platform": platform.platform(), "cpus": torch.get_num_threads(),
                                                    "torch": torch.__version__}, "cases": rows,
            "peak_memory_mb": peak_memory_mb()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m wgs.bench")
    ap.add_argument("which", choices=["rasterizer"])
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--ref-repeats", type=int, default=3)
    a = ap.parse_args(argv)
    res = bench_rasterizer(a.repeats, a.ref_repeats)
    if a.json:
        json.dump(res, sys.stdout, indent=2)
        print()
        return
    print(f"{'case':>14} {'backend':>10} {'fwd median':>11} {'fwd+bwd median':>15} {'(min..max)':>18}")
    for r in res["cases"]:
        for be in ("numba", "torch_reference"):
            f, b = r[be]["forward"], r[be]["forward_backward"]
            print(f"{r['size']}px x {r['gaussians']:>6} {be:>10} {f['median_s']:>10.4f}s {b['median_s']:>14.4f}s"
                  f"  ({b['min_s']:.4f}..{b['max_s']:.4f})")
        print(f"{'':>14} speed-up (fwd+bwd): {r['speedup_forward_backward']:.1f}x")
    print(f"peak memory: {res['peak_memory_mb']:.0f} MiB")


if __name__ == "__main__":
    main()
