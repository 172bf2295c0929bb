"""CPU fast path: tile-based forward and backward rasterization kernels in numba.

Same semantics as `raster_torch.rasterize_pixels_torch` (the tests compare them). Work is split
over 16x16 tiles (numba prange); each (tile, Gaussian) pair owns one row of the backward buffer,
so threads never write the same memory and the result is deterministic; rows are summed per
Gaussian with `index_add_`. Kernels are compiled once and cached on disk (`cache=True`;
`NUMBA_CACHE_DIR` moves the cache).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from .raster_torch import ALPHA_MAX, ALPHA_MIN, POWER_MIN, T_MIN, depth_order

TILE = 16
NG = 6  # per-entry gradient slots before the colours: mean x, mean y, conic a, b, c, opacity
COORD_LIMIT = 1e8  # px; keeps tile arithmetic in range for absurd footprints
# float32 constants: the per-pair Gaussian stays in float32 (expf), transmittance in float64
F_HALF = np.float32(0.5)
F_POWER_MIN = np.float32(POWER_MIN)
F_ALPHA_MAX = np.float32(ALPHA_MAX)
F_ALPHA_MIN = np.float32(ALPHA_MIN)
F_ZERO = np.float32(0.0)


@nb.njit(cache=True)
def _bin_tiles(means2d, extents, order, width, height, tile):
    """Tile lists: Gaussian ids sorted by tile, front to back within a tile (`order` is sorted)."""
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    V = order.shape[0]
    rect = np.empty((V, 4), np.int64)
    counts = np.zeros(n_tiles + 1, np.int64)
    for j in range(V):
        g = order[j]
        # pixel centres are at x + 0.5; small slack so float rounding never drops a pixel
        ex = extents[g, 0] * 1.0001 + 0.01
        ey = extents[g, 1] * 1.0001 + 0.01
        lo_x = min(max(means2d[g, 0] - ex - 0.5, -COORD_LIMIT), COORD_LIMIT)
        hi_x = min(max(means2d[g, 0] + ex - 0.5, -COORD_LIMIT), COORD_LIMIT)
        lo_y = min(max(means2d[g, 1] - ey - 0.5, -COORD_LIMIT), COORD_LIMIT)
        hi_y = min(max(means2d[g, 1] + ey - 0.5, -COORD_LIMIT), COORD_LIMIT)
        tx0 = max(0, int(math.floor(lo_x / tile)))
        tx1 = min(tiles_x, int(math.floor(hi_x / tile)) + 1)
        ty0 = max(0, int(math.floor(lo_y / tile)))
        ty1 = min(tiles_y, int(math.floor(hi_y / tile)) + 1)
        rect[j, 0], rect[j, 1], rect[j, 2], rect[j, 3] = tx0, tx1, ty0, ty1
        for ty in range(ty0, ty1):
            for tx in range(tx0, tx1):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    fill = counts[:-1].copy()
    ids = np.empty(counts[n_tiles], np.int64)
    for j in range(V):
        g = order[j]
        for ty in range(rect[j, 2], rect[j, 3]):
            for tx in range(rect[j, 0], rect[j, 1]):
                t = ty * tiles_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return ids, counts


@nb.njit(cache=True)
def _gather(ids, means2d, conics, opacities, colors):
    """Per-entry copies of the Gaussian parameters, so the kernels read memory in order."""
    M = ids.shape[0]
    D = colors.shape[1]
    P = np.empty((M, 6 + D), np.float32)
    for k in range(M):
        g = ids[k]
        P[k, 0] = means2d[g, 0]
        P[k, 1] = means2d[g, 1]
        P[k, 2] = conics[g, 0]
        P[k, 3] = conics[g, 1]
        P[k, 4] = conics[g, 2]
        P[k, 5] = opacities[g]
        for c in range(D):
            P[k, 6 + c] = colors[g, c]
    return P


@nb.njit(parallel=True, cache=True, fastmath=True)
def _forward(P, offsets, bg, width, height, tile, out_color, out_T, out_last):
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    D = bg.shape[0]
    for t in nb.prange(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        e = offsets[t + 1]
        for py in range(ty * tile, min(height, ty * tile + tile)):
            fy = np.float32(py) + F_HALF
            for px in range(tx * tile, min(width, tx * tile + tile)):
                fx = np.float32(px) + F_HALF
                T = 1.0
                last = s
                for k in range(s, e):
                    dx = fx - P[k, 0]
                    dy = fy - P[k, 1]
                    power = -F_HALF * (P[k, 2] * dx * dx + P[k, 4] * dy * dy) - P[k, 3] * dx * dy
                    if power > F_ZERO or power < F_POWER_MIN:
                        continue
                    al = min(F_ALPHA_MAX, P[k, 5] * math.exp(power))
                    if al < F_ALPHA_MIN:
                        continue
                    nT = T * (1.0 - al)
                    if nT < T_MIN:
                        break
                    w = al * T
                    for c in range(D):
                        out_color[py, px, c] += w * P[k, 6 + c]
                    T = nT
                    last = k + 1
                for c in range(D):
                    out_color[py, px, c] += T * bg[c]
                out_T[py, px] = T
                out_last[py, px] = last


@nb.njit(parallel=True, cache=True, fastmath=True)
def _backward(P, offsets, bg, width, height, tile, out_T, out_last, g_color, g_alpha, G):
    tiles_x = (width + tile - 1) // tile
    n_tiles = offsets.shape[0] - 1
    D = bg.shape[0]
    for t in nb.prange(n_tiles):
        ty = t // tiles_x
        tx = t - ty * tiles_x
        s = offsets[t]
        accum = np.zeros(D)
        lastc = np.zeros(D)
        for py in range(ty * tile, min(height, ty * tile + tile)):
            fy = np.float32(py) + F_HALF
            for px in range(tx * tile, min(width, tx * tile + tile)):
                last = out_last[py, px]
                if last == s:
                    continue
                fx = np.float32(px) + F_HALF
                Tf = out_T[py, px]
                T = Tf
                bgdot = 0.0
                for c in range(D):
                    bgdot += bg[c] * g_color[py, px, c]
                    accum[c] = 0.0
                    lastc[c] = 0.0
                gA = g_alpha[py, px]
                last_al = 0.0
                for k in range(last - 1, s - 1, -1):
                    dx = fx - P[k, 0]
                    dy = fy - P[k, 1]
                    power = -F_HALF * (P[k, 2] * dx * dx + P[k, 4] * dy * dy) - P[k, 3] * dx * dy
                    if power > F_ZERO or power < F_POWER_MIN:
                        continue
                    gauss = math.exp(power)
                    raw = P[k, 5] * gauss
                    al = min(F_ALPHA_MAX, raw)
                    if al < F_ALPHA_MIN:
                        continue
                    inv = 1.0 / (1.0 - al)
                    T = T * inv
                    d_al = 0.0
                    for c in range(D):
                        accum[c] = last_al * lastc[c] + (1.0 - last_al) * accum[c]
                        lastc[c] = P[k, 6 + c]
                        d_al += (P[k, 6 + c] - accum[c]) * g_color[py, px, c]
                        G[k, NG + c] += al * T * g_color[py, px, c]
                    d_al *= T
                    last_al = al
                    d_al += (gA - bgdot) * Tf * inv
                    if raw <= F_ALPHA_MAX:
                        d_pow = d_al * al
                        G[k, 0] += d_pow * (P[k, 2] * dx + P[k, 3] * dy)
                        G[k, 1] += d_pow * (P[k, 3] * dx + P[k, 4] * dy)
                        G[k, 2] += -0.5 * d_pow * dx * dx
                        G[k, 3] += -d_pow * dx * dy
                        G[k, 4] += -0.5 * d_pow * dy * dy
                        G[k, 5] += d_al * gauss


def _np32(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to("cpu", torch.float32).numpy())


class RasterizeNumba(torch.autograd.Function):
    """(means2d, conics, colors, opacities, depths, extents, visible, W, H, background) -> color, alpha."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, extents, visible, width, height, background):
        order = depth_order(depths, visible).cpu().numpy().astype(np.int64)
        m2, ext = _np32(means2d), _np32(extents)
        ids, offsets = _bin_tiles(m2, ext, order, width, height, TILE)
        P = _gather(ids, m2, _np32(conics), _np32(opacities), _np32(colors))
        D = colors.shape[1]
        bg = np.ascontiguousarray(background.detach().cpu().numpy().astype(np.float64))
        out_color = np.zeros((height, width, D), np.float32)
        out_T = np.empty((height, width), np.float64)
        out_last = np.empty((height, width), np.int64)
        _forward(P, offsets, bg, width, height, TILE, out_color, out_T, out_last)
        ctx.state = (ids, offsets, P, bg, width, height, out_T, out_last, means2d.shape[0], D, means2d.dtype)
        dev = means2d.device
        color = torch.from_numpy(out_color).to(dev)
        alpha = torch.from_numpy((1.0 - out_T).astype(np.float32))[..., None].to(dev)
        return color, alpha

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        ids, offsets, P, bg, width, height, out_T, out_last, N, D, dtype = ctx.state
        gc = np.ascontiguousarray(g_color.detach().cpu().numpy().astype(np.float64))
        ga = np.ascontiguousarray(g_alpha.detach().cpu().numpy()[..., 0].astype(np.float64))
        G = np.zeros((ids.shape[0], NG + D), np.float32)  # float32 halves the memory traffic
        _backward(P, offsets, bg, width, height, TILE, out_T, out_last, gc, ga, G)
        acc = torch.zeros(N, NG + D, dtype=torch.float32).index_add_(0, torch.from_numpy(ids), torch.from_numpy(G))
        dev = g_color.device
        acc = acc.to(device=dev, dtype=dtype)
        return (acc[:, 0:2], acc[:, 2:5], acc[:, NG:], acc[:, 5], None, None, None, None, None, None)


def rasterize_pixels_numba(means2d, conics, colors, opacities, depths, extents, visible, width, height,
                           background):
    """Numba fast path; same arguments and outputs as `rasterize_pixels_torch`."""
    return RasterizeNumba.apply(means2d, conics, colors, opacities, depths, extents, visible, int(width),
                                int(height), background)
