"""CPU fast path: tile-based forward and backward rasterization kernels in numba.

Same semantics as `raster_torch.rasterize_pixels_torch` (the tests compare them). Work is split
over 16x16 tiles (numba prange). A Gaussian is listed in the tiles that its reach ellipse meets
(alpha >= 1/255 and within 3 sigma: where the kernels could draw it), and inside a tile it visits
only the pixels of its box, front to back for the forward, back to front for the backward, with
the per-pixel state (transmittance, colour sums) in tile arrays. Each (tile, Gaussian) pair owns
one row of the backward buffer, so threads never write the same memory and the result is
deterministic; rows are summed per Gaussian in entry order (`_sum_per_gaussian`). Binning, the
per-entry copies and those sums run in parallel too. Kernels are compiled once and cached on disk
(`cache=True`; `NUMBA_CACHE_DIR` moves the cache).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from .raster_torch import ALPHA_MAX, ALPHA_MIN, POWER_MIN, T_MIN, depth_order

TILE = 16
NG = 6  # per-entry gradient slots before the colours: mean x, mean y, conic a, b, c, opacity
NP = 8  # per-entry parameter slots before the colours: the six above and the half box x, y
COORD_LIMIT = 1e8  # px; keeps tile arithmetic in range for absurd footprints
# float32 constants: the per-pair Gaussian stays in float32 (expf), transmittance in float64
F_HALF = np.float32(0.5)
F_POWER_MIN = np.float32(POWER_MIN)
F_ALPHA_MAX = np.float32(ALPHA_MAX)
F_ALPHA_MIN = np.float32(ALPHA_MIN)
F_ZERO = np.float32(0.0)


@nb.njit(cache=True, inline="always")
def _reach(A, B, C, op, cap_x, cap_y):
    """Squared Mahalanobis reach r2 of a Gaussian (conic A, B, C; power = -(A dx^2 + 2B dx dy +
    C dy^2) / 2) and its half box (ex, ey) in px. Beyond r2 a pixel gets alpha < 1/255 (opacity
    `op`) or lies past the 3-sigma cut, so the kernels skip it anyway: the box is exact, and smaller
    than the 3-sigma box for all but opaque Gaussians. r2 < 0: the Gaussian is never drawn."""
    if not op * 255.0 >= 1.0:  # (also NaN)
        return -1.0, 0.0, 0.0
    r2 = min(-2.0 * POWER_MIN, 2.0 * math.log(op * 255.0))  # alpha = min(0.99, op g) >= 1/255 iff op g >= 1/255
    det = A * C - B * B
    if not det > 0.0:
        return -1.0, 0.0, 0.0
    ex = min(math.sqrt(r2 * C / det), cap_x) * 1.0001 + 0.01  # slack: float rounding never drops a pixel
    ey = min(math.sqrt(r2 * A / det), cap_y) * 1.0001 + 0.01
    return r2, ex, ey


@nb.njit(cache=True, inline="always")
def _edge_min(A, B, C, u, v0, v1):
    """min over v in [v0, v1] of A u^2 + 2 B u v + C v^2 (C > 0)."""
    v = min(max(-B * u / C, v0), v1)
    return A * u * u + 2.0 * B * u * v + C * v * v


@nb.njit(cache=True)
def _touches(A, B, C, r2, x0, x1, y0, y1):
    """Does the ellipse A dx^2 + 2B dx dy + C dy^2 <= r2 (centred at 0) meet the box [x0, x1] x [y0, y1]?"""
    if x0 <= 0.0 <= x1 and y0 <= 0.0 <= y1:
        return True
    q = min(_edge_min(A, B, C, x0, y0, y1), _edge_min(A, B, C, x1, y0, y1))
    q = min(q, _edge_min(C, B, A, y0, x0, x1), _edge_min(C, B, A, y1, x0, x1))
    return q <= r2 * 1.0002 + 1e-4


@nb.njit(parallel=True, cache=True)
def _bin_tiles(means2d, conics, opacities, extents, order, width, height, tile, boxes):
    """Tile lists: Gaussian ids sorted by tile, front to back within a tile (`order` is sorted).
    A Gaussian goes to the tiles its reach ellipse meets (not every tile of its box); `boxes`
    [N, 2] receives each Gaussian's half box in px. Also returns, for each Gaussian, its entries
    in increasing order (`by_gaussian`, `starts` [N + 1]) for the backward's per-Gaussian sums.

    The reach and the ellipse-tile tests run in parallel over Gaussians, each writing its hits into
    its own slice (one slot per tile of its box); a serial counting sort then puts the hits, in
    depth order, into their tiles."""
    tiles_x = (width + tile - 1) // tile
    tiles_y = (height + tile - 1) // tile
    n_tiles = tiles_x * tiles_y
    V = order.shape[0]
    N = means2d.shape[0]
    rect = np.zeros((V, 4), np.int64)
    box_tiles = np.zeros(V + 1, np.int64)
    for j in nb.prange(V):
        g = order[j]
        A, B, C = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        r2, ex, ey = _reach(A, B, C, np.float64(opacities[g]), extents[g, 0], extents[g, 1])
        boxes[g, 0], boxes[g, 1], boxes[g, 2] = ex, ey, r2
        if r2 < 0.0:
            continue
        mx, my = np.float64(means2d[g, 0]), np.float64(means2d[g, 1])
        # pixel centres are at x + 0.5
        lo_x = min(max(mx - ex - 0.5, -COORD_LIMIT), COORD_LIMIT)
        hi_x = min(max(mx + ex - 0.5, -COORD_LIMIT), COORD_LIMIT)
        lo_y = min(max(my - ey - 0.5, -COORD_LIMIT), COORD_LIMIT)
        hi_y = min(max(my + ey - 0.5, -COORD_LIMIT), COORD_LIMIT)
        tx0 = max(0, int(math.floor(lo_x / tile)))
        tx1 = min(tiles_x, int(math.floor(hi_x / tile)) + 1)
        ty0 = max(0, int(math.floor(lo_y / tile)))
        ty1 = min(tiles_y, int(math.floor(hi_y / tile)) + 1)
        rect[j, 0], rect[j, 1], rect[j, 2], rect[j, 3] = tx0, tx1, ty0, ty1
        box_tiles[j + 1] = max(0, tx1 - tx0) * max(0, ty1 - ty0)
    for j in range(V):
        box_tiles[j + 1] += box_tiles[j]
    hits = np.empty(box_tiles[V], np.int64)
    n_hits = np.zeros(V, np.int64)
    for j in nb.prange(V):
        g = order[j]
        A, B, C = np.float64(conics[g, 0]), np.float64(conics[g, 1]), np.float64(conics[g, 2])
        mx, my = np.float64(means2d[g, 0]), np.float64(means2d[g, 1])
        m = box_tiles[j]
        for ty in range(rect[j, 2], rect[j, 3]):
            y0 = ty * tile + 0.5 - my
            y1 = min(height, ty * tile + tile) - 0.5 - my
            for tx in range(rect[j, 0], rect[j, 1]):
                if _touches(
                    A, B, C, boxes[g, 2], tx * tile + 0.5 - mx, min(width, tx * tile + tile) - 0.5 - mx, y0, y1
                ):
                    hits[m] = ty * tiles_x + tx
                    m += 1
        n_hits[j] = m - box_tiles[j]
    counts = np.zeros(n_tiles + 1, np.int64)
    per_g = np.zeros(N + 1, np.int64)
    for j in range(V):
        per_g[order[j] + 1] = n_hits[j]
        for q in range(box_tiles[j], box_tiles[j] + n_hits[j]):
            counts[hits[q] + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    for g in range(N):
        per_g[g + 1] += per_g[g]
    fill = counts[:-1].copy()
    ids = np.empty(counts[n_tiles], np.int64)
    for j in range(V):
        g = order[j]
        for q in range(box_tiles[j], box_tiles[j] + n_hits[j]):
            t = hits[q]
            ids[fill[t]] = g
            fill[t] += 1
    # entries of each Gaussian, in increasing entry order
    fill_g = per_g[:-1].copy()
    by_gaussian = np.empty(counts[n_tiles], np.int64)
    for k in range(counts[n_tiles]):
        g = ids[k]
        by_gaussian[fill_g[g]] = k
        fill_g[g] += 1
    return ids, counts, by_gaussian, per_g


@nb.njit(parallel=True, cache=True)
def _gather(ids, means2d, conics, opacities, colors, boxes):
    """Per-entry copies of the Gaussian parameters, so the kernels read memory in order:
    mean x, y, conic a, b, c, opacity, half box x, y, colours."""
    M = ids.shape[0]
    D = colors.shape[1]
    P = np.empty((M, NP + D), np.float32)
    for k in nb.prange(M):
        g = ids[k]
        P[k, 0] = means2d[g, 0]
        P[k, 1] = means2d[g, 1]
        P[k, 2] = conics[g, 0]
        P[k, 3] = conics[g, 1]
        P[k, 4] = conics[g, 2]
        P[k, 5] = opacities[g]
        P[k, 6] = boxes[g, 0]
        P[k, 7] = boxes[g, 1]
        for c in range(D):
            P[k, NP + c] = colors[g, c]
    return P


@nb.njit(parallel=True, cache=True)
def _sum_per_gaussian(G, by_gaussian, starts):
    """[N, C] sums of the backward's entry rows per Gaussian, each in increasing entry order
    (deterministic; the same sums as a serial `index_add_`)."""
    N = starts.shape[0] - 1
    out = np.zeros((N, G.shape[1]), np.float32)
    for g in nb.prange(N):
        for q in range(starts[g], starts[g + 1]):
            k = by_gaussian[q]
            for c in range(G.shape[1]):
                out[g, c] += G[k, c]
    return out


def _depth_order(depths: torch.Tensor, visible: torch.Tensor) -> np.ndarray:
    """`raster_torch.depth_order` (its reference) as int64 numpy: one sort of keys (float32 depth
    bits, index), unique, so the order is the stable one. Visible depths are > 0, where the
    float's bits sort as the float does; other dtypes take the reference."""
    if depths.dtype != torch.float32:
        return depth_order(depths, visible).cpu().numpy().astype(np.int64)
    idx = np.flatnonzero(visible.detach().cpu().numpy())
    bits = depths.detach().cpu().numpy()[idx].view(np.int32).astype(np.int64)
    keys = (bits << 32) | idx
    keys.sort()
    return keys & 0xFFFFFFFF


@nb.njit(cache=True, inline="always")
def _span(P, k, x0, x1, y0, y1):
    """Pixels [px0, px1) x [py0, py1) of tile [x0, x1) x [y0, y1) inside entry k's box."""
    px0 = max(x0, int(math.ceil(P[k, 0] - P[k, 6] - 0.5)))
    px1 = min(x1, int(math.floor(P[k, 0] + P[k, 6] - 0.5)) + 1)
    py0 = max(y0, int(math.ceil(P[k, 1] - P[k, 7] - 0.5)))
    py1 = min(y1, int(math.floor(P[k, 1] + P[k, 7] - 0.5)) + 1)
    return px0, px1, py0, py1


@nb.njit(cache=True, inline="always")
def _tile_box(t, width, height, tile):
    """Pixel box [x0, x1) x [y0, y1) of tile t (row-major tiles of `tile` pixels, cut at the image edge)."""
    tiles_x = (width + tile - 1) // tile
    ty = t // tiles_x
    x0, y0 = (t - ty * tiles_x) * tile, ty * tile
    return x0, min(width, x0 + tile), y0, min(height, y0 + tile)


@nb.njit(parallel=True, cache=True, fastmath=True)
def _forward(P, offsets, bg, width, height, tile, out_color, out_T, out_last):
    """Gaussian-outer within a tile: each entry visits only the pixels of its box, front to back,
    with the tile's transmittance kept per pixel (the same sums, in the same order per pixel, as
    looping over the entries per pixel)."""
    D = bg.shape[0]
    for t in nb.prange(offsets.shape[0] - 1):
        s = offsets[t]
        e = offsets[t + 1]
        x0, x1, y0, y1 = _tile_box(t, width, height, tile)
        T = np.ones((tile, tile))
        last = np.full((tile, tile), s, np.int64)
        done = np.zeros((tile, tile), np.bool_)
        acc = np.zeros((tile, tile, D), np.float32)
        n_open = (x1 - x0) * (y1 - y0)
        for k in range(s, e):
            if n_open == 0:
                break
            px0, px1, py0, py1 = _span(P, k, x0, x1, y0, y1)
            for py in range(py0, py1):
                dy = np.float32(py) + F_HALF - P[k, 1]
                for px in range(px0, px1):
                    i, j = py - y0, px - x0
                    if done[i, j]:
                        continue
                    dx = np.float32(px) + F_HALF - P[k, 0]
                    power = -F_HALF * (P[k, 2] * dx * dx + P[k, 4] * dy * dy) - P[k, 3] * dx * dy
                    if power > F_ZERO or power < F_POWER_MIN:
                        continue
                    al = min(F_ALPHA_MAX, P[k, 5] * math.exp(power))
                    if al < F_ALPHA_MIN:
                        continue
                    nT = T[i, j] * (1.0 - al)
                    if nT < T_MIN:
                        done[i, j] = True
                        n_open -= 1
                        continue
                    w = al * T[i, j]
                    for c in range(D):
                        acc[i, j, c] += w * P[k, NP + c]
                    T[i, j] = nT
                    last[i, j] = k + 1
        for py in range(y0, y1):
            for px in range(x0, x1):
                i, j = py - y0, px - x0
                for c in range(D):
                    out_color[py, px, c] = acc[i, j, c] + T[i, j] * bg[c]
                out_T[py, px] = T[i, j]
                out_last[py, px] = last[i, j]


@nb.njit(parallel=True, cache=True, fastmath=True)
def _backward(P, offsets, bg, width, height, tile, out_T, out_last, g_color, g_alpha, G):
    """Gaussian-outer, back to front, per-pixel state in tile arrays; each entry's gradient row is
    summed over its pixels in row-major order and written once (no two threads share a row)."""
    D = bg.shape[0]
    for t in nb.prange(offsets.shape[0] - 1):
        s = offsets[t]
        x0, x1, y0, y1 = _tile_box(t, width, height, tile)
        T = np.empty((tile, tile))
        accum = np.zeros((tile, tile, D))
        lastc = np.zeros((tile, tile, D))
        last_al = np.zeros((tile, tile))
        bgterm = np.empty((tile, tile))
        top = s  # the highest `last` of the tile: entries at or above it touch no pixel
        for py in range(y0, y1):
            for px in range(x0, x1):
                i, j = py - y0, px - x0
                T[i, j] = out_T[py, px]
                bgdot = 0.0
                for c in range(D):
                    bgdot += bg[c] * g_color[py, px, c]
                bgterm[i, j] = (g_alpha[py, px] - bgdot) * out_T[py, px]
                top = max(top, out_last[py, px])
        g = np.empty(NG + D)
        for k in range(top - 1, s - 1, -1):
            px0, px1, py0, py1 = _span(P, k, x0, x1, y0, y1)
            for q in range(NG + D):
                g[q] = 0.0
            hit = False
            for py in range(py0, py1):
                dy = np.float32(py) + F_HALF - P[k, 1]
                for px in range(px0, px1):
                    if k >= out_last[py, px]:
                        continue
                    i, j = py - y0, px - x0
                    dx = np.float32(px) + F_HALF - P[k, 0]
                    power = -F_HALF * (P[k, 2] * dx * dx + P[k, 4] * dy * dy) - P[k, 3] * dx * dy
                    if power > F_ZERO or power < F_POWER_MIN:
                        continue
                    gauss = math.exp(power)
                    raw = P[k, 5] * gauss
                    al = min(F_ALPHA_MAX, raw)
                    if al < F_ALPHA_MIN:
                        continue
                    hit = True
                    inv = 1.0 / (1.0 - al)
                    T[i, j] = T[i, j] * inv
                    Tij = T[i, j]
                    la = last_al[i, j]
                    d_al = 0.0
                    for c in range(D):
                        gc = g_color[py, px, c]
                        a_c = la * lastc[i, j, c] + (1.0 - la) * accum[i, j, c]
                        accum[i, j, c] = a_c
                        col = P[k, NP + c]
                        lastc[i, j, c] = col
                        d_al += (col - a_c) * gc
                        g[NG + c] += al * Tij * gc
                    d_al = d_al * Tij + bgterm[i, j] * inv
                    last_al[i, j] = al
                    if raw <= F_ALPHA_MAX:
                        d_pow = d_al * al
                        g[0] += d_pow * (P[k, 2] * dx + P[k, 3] * dy)
                        g[1] += d_pow * (P[k, 3] * dx + P[k, 4] * dy)
                        g[2] += -0.5 * d_pow * dx * dx
                        g[3] += -d_pow * dx * dy
                        g[4] += -0.5 * d_pow * dy * dy
                        g[5] += d_al * gauss
            if hit:
                for q in range(NG + D):
                    G[k, q] = g[q]


def _np32(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to("cpu", torch.float32).numpy())


class RasterizeNumba(torch.autograd.Function):
    """(means2d, conics, colors, opacities, depths, extents, visible, W, H, background) -> color, alpha."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, extents, visible, width, height, background):
        order = _depth_order(depths, visible)
        m2, ext, con, op = _np32(means2d), _np32(extents), _np32(conics), _np32(opacities)
        boxes = np.zeros((means2d.shape[0], 3))
        ids, offsets, by_gaussian, starts = _bin_tiles(m2, con, op, ext, order, width, height, TILE, boxes)
        P = _gather(ids, m2, con, op, _np32(colors), boxes)
        D = colors.shape[1]
        bg = np.ascontiguousarray(background.detach().cpu().numpy().astype(np.float64))
        out_color = np.zeros((height, width, D), np.float32)
        out_T = np.empty((height, width), np.float64)
        out_last = np.empty((height, width), np.int64)
        _forward(P, offsets, bg, width, height, TILE, out_color, out_T, out_last)
        ctx.state = (
            by_gaussian,
            starts,
            offsets,
            P,
            bg,
            width,
            height,
            out_T,
            out_last,
            means2d.shape[0],
            D,
            means2d.dtype,
        )
        dev = means2d.device
        color = torch.from_numpy(out_color).to(dev)
        alpha = torch.from_numpy((1.0 - out_T).astype(np.float32))[..., None].to(dev)
        return color, alpha

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        by_gaussian, starts, offsets, P, bg, width, height, out_T, out_last, N, D, dtype = ctx.state
        gc = np.ascontiguousarray(g_color.detach().cpu().numpy().astype(np.float64))
        ga = np.ascontiguousarray(g_alpha.detach().cpu().numpy()[..., 0].astype(np.float64))
        G = np.zeros((P.shape[0], NG + D), np.float32)  # float32 halves the memory traffic
        _backward(P, offsets, bg, width, height, TILE, out_T, out_last, gc, ga, G)
        acc = torch.from_numpy(_sum_per_gaussian(G, by_gaussian, starts))
        dev = g_color.device
        acc = acc.to(device=dev, dtype=dtype)
        return (acc[:, 0:2], acc[:, 2:5], acc[:, NG:], acc[:, 5], None, None, None, None, None, None)


def rasterize_pixels_numba(means2d, conics, colors, opacities, depths, extents, visible, width, height, background):
    """Numba fast path; same arguments and outputs as `rasterize_pixels_torch`."""
    return RasterizeNumba.apply(
        means2d, conics, colors, opacities, depths, extents, visible, int(width), int(height), background
    )
