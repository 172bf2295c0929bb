"""CUDA check: the torch reference rasterizer on CUDA against the CPU (float64), and the speed of a
200x200 render (forward + backward) on CUDA (torch reference) and on the CPU (numba).

    python tools/experiments/xp_cuda_parity.py
"""

import time

import torch

from wgs.gaussians.render import rasterize


def scene(n, dev, dt, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 1.0
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.03 + 0.005
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.8 + 0.1
    cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[2, 3] = 3.0
    K = torch.tensor([[220.0, 0, 100], [0, 220.0, 100], [0, 0, 1]], dtype=torch.float64)
    ts = [t.to(dev, dt) for t in (means, quats, scales, opac, cols, view, K)]
    for t in ts[:5]:
        t.requires_grad_(True)
    return ts


def run(dev, dt, n=2000, backend="torch"):
    m, q, s, o, c, v, K = scene(n, dev, dt)
    rgb, a, _ = rasterize(m, q, s, o, c, v, K, 200, 200, backend=backend)
    (rgb.square().sum() + a.sum()).backward()
    return rgb.detach().cpu().double(), a.detach().cpu().double(), [t.grad.cpu().double() for t in (m, q, s, o, c)]


def timed(dev, n, backend, repeats):
    for _ in range(3):
        run(dev, torch.float32, n, backend)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(repeats):
        run(dev, torch.float32, n, backend)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t) / repeats * 1e3


if not torch.cuda.is_available():  # the CPU's figures, for the comparison
    for n in (15000, 50000):
        print(f"cpu numba 200x200 {n} Gaussians forward+backward: {timed(torch.device('cpu'), n, 'numba', 5):.1f} ms")
    raise SystemExit("no CUDA device: only the CPU timing")
cpu = run(torch.device("cpu"), torch.float64)
for dt in (torch.float64, torch.float32):
    gpu = run(torch.device("cuda"), dt)
    pairs = zip([gpu[0], gpu[1], *gpu[2]], [cpu[0], cpu[1], *cpu[2]], strict=True)
    err = [float((x - y).abs().max() / (y.abs().max() + 1e-12)) for x, y in pairs]
    print(
        f"cuda {dt} vs cpu float64, max rel error rgb alpha d_means d_quats d_scales d_opac d_colors:",
        " ".join(f"{e:.1e}" for e in err),
    )
backends = ["torch"]
try:
    t0 = time.perf_counter()
    run(torch.device("cuda"), torch.float32, 100, "gsplat")  # gsplat compiles its kernels on first use
    print(f"gsplat ready in {time.perf_counter() - t0:.0f} s")
    backends.append("gsplat")
    ref, ours = (
        run(torch.device("cuda"), torch.float32, 2000, "torch"),
        run(torch.device("cuda"), torch.float32, 2000, "gsplat"),
    )
    print(
        "gsplat vs torch reference (float32), max abs difference rgb alpha:",
        f"{float((ref[0] - ours[0]).abs().max()):.1e} {float((ref[1] - ours[1]).abs().max()):.1e}",
    )
except Exception as exc:  # not installed, or its kernels did not build
    print(f"gsplat unavailable: {exc!r}"[:400])
for backend in backends:
    for n in (15000, 50000):
        print(
            f"cuda {backend} 200x200 {n} Gaussians forward+backward: "
            f"{timed(torch.device('cuda'), n, backend, 20):.1f} ms"
        )
