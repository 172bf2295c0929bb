"""CPU fast path of `project.project_gaussians`: the EWA projection and its backward pass as two
numba kernels, one Gaussian per loop iteration, float64 inside (as the reference).

The reference builds a graph of ~40 small tensor ops whose autograd cost more than the
rasterizer itself on small images; here the backward recomputes the forward per Gaussian and
applies the chain rule by hand. Gradients flow to means, quats and scales only (the camera is
fixed); `tests/test_project_numba.py` checks values and gradients against the reference.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from .project import BLUR, SIGMA_CUT, Projected


@nb.njit(cache=True, inline="always")
def _unit_quat(q):
    w, x, y, z = q[0], q[1], q[2], q[3]
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n > 1e-12:
        return w / n, x / n, y / n, z / n, n
    return 1.0, 0.0, 0.0, 0.0, 0.0


@nb.njit(cache=True, inline="always")
def _rotmat(w, x, y, z, R):
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@nb.njit(cache=True, inline="always")
def _setup(i, means, quats, scales, V, cam, near, far, Rq, M, S, T, TS):
    """Per-Gaussian forward quantities into the scratch arrays; returns (px, py, z, zs, tx, ty,
    x_clamped, y_clamped, in_depth, a, b, c)."""
    w, x, y, z, _ = _unit_quat(quats[i])
    _rotmat(w, x, y, z, Rq)
    for r in range(3):
        for k in range(3):
            M[r, k] = Rq[r, k] * scales[i, k]
    for r in range(3):
        for k in range(3):
            S[r, k] = M[r, 0] * M[k, 0] + M[r, 1] * M[k, 1] + M[r, 2] * M[k, 2]
    p = np.empty(3)
    for r in range(3):
        p[r] = V[r, 0] * means[i, 0] + V[r, 1] * means[i, 1] + V[r, 2] * means[i, 2] + V[r, 3]
    fx, fy, lim_xp, lim_xn, lim_yp, lim_yn = cam[0], cam[1], cam[4], cam[5], cam[6], cam[7]
    zc = p[2]
    in_depth = zc > near and zc < far
    zs = zc if in_depth else 1.0
    ux, uy = p[0] / zs, p[1] / zs
    x_cl = not (ux > -lim_xn and ux < lim_xp)
    y_cl = not (uy > -lim_yn and uy < lim_yp)
    tx = zs * min(max(ux, -lim_xn), lim_xp)
    ty = zs * min(max(uy, -lim_yn), lim_yp)
    j00, j02 = fx / zs, -fx * tx / (zs * zs)
    j11, j12 = fy / zs, -fy * ty / (zs * zs)
    for k in range(3):
        T[0, k] = j00 * V[0, k] + j02 * V[2, k]
        T[1, k] = j11 * V[1, k] + j12 * V[2, k]
    for r in range(2):
        for k in range(3):
            TS[r, k] = T[r, 0] * S[0, k] + T[r, 1] * S[1, k] + T[r, 2] * S[2, k]
    a = TS[0, 0] * T[0, 0] + TS[0, 1] * T[0, 1] + TS[0, 2] * T[0, 2] + BLUR
    b = TS[0, 0] * T[1, 0] + TS[0, 1] * T[1, 1] + TS[0, 2] * T[1, 2]
    c = TS[1, 0] * T[1, 0] + TS[1, 1] * T[1, 1] + TS[1, 2] * T[1, 2] + BLUR
    return p[0], p[1], zc, zs, tx, ty, x_cl, y_cl, in_depth, a, b, c


@nb.njit(parallel=True, cache=True)
def _project_forward(means, quats, scales, V, cam, width, height, near, far, out):
    """out [N, 9]: means2d (2), conics (3), depth, extents (2), visible (0/1)."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for i in nb.prange(means.shape[0]):
        Rq, M, S = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        T, TS = np.empty((2, 3)), np.empty((2, 3))
        px, py, zc, zs, tx, ty, x_cl, y_cl, in_depth, a, b, c = _setup(
            i, means, quats, scales, V, cam, near, far, Rq, M, S, T, TS
        )
        det = a * c - b * b
        mx, my = fx * px / zs + cx, fy * py / zs + cy
        ex, ey = SIGMA_CUT * math.sqrt(max(a, 0.0)), SIGMA_CUT * math.sqrt(max(c, 0.0))
        ok = (
            in_depth
            and det > 0
            and math.isfinite(det)
            and mx + ex > 0
            and mx - ex < width
            and my + ey > 0
            and my - ey < height
            and math.isfinite(mx)
            and math.isfinite(my)
        )
        out[i, 5] = zc
        if ok:
            out[i, 0], out[i, 1] = mx, my
            out[i, 2], out[i, 3], out[i, 4] = c / det, -b / det, a / det
            out[i, 6], out[i, 7] = ex, ey
            out[i, 8] = 1.0
        else:
            for k in (0, 1, 2, 3, 4, 6, 7, 8):
                out[i, k] = 0.0


@nb.njit(parallel=True, cache=True)
def _project_backward(means, quats, scales, V, cam, near, far, visible, g_m, g_c, g_means, g_quats, g_scales):
    fx, fy = cam[0], cam[1]
    for i in nb.prange(means.shape[0]):
        if not visible[i]:
            continue
        Rq, M, S = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        T, TS = np.empty((2, 3)), np.empty((2, 3))
        px, py, zc, zs, tx, ty, x_cl, y_cl, in_depth, a, b, c = _setup(
            i, means, quats, scales, V, cam, near, far, Rq, M, S, T, TS
        )
        det = a * c - b * b
        q0, q1, q2 = c / det, -b / det, a / det
        g0, g1, g2 = g_c[i, 0], 0.5 * g_c[i, 1], g_c[i, 2]
        # conic = inverse(cov2d): dL/dcov = -Q G Q (G symmetric, off-diagonal halves)
        u00, u01 = q0 * g0 + q1 * g1, q0 * g1 + q1 * g2
        u10, u11 = q1 * g0 + q2 * g1, q1 * g1 + q2 * g2
        G00 = -(u00 * q0 + u01 * q1)
        G01 = -(u00 * q1 + u01 * q2)
        G11 = -(u10 * q1 + u11 * q2)
        Gc = np.empty((2, 2))
        Gc[0, 0], Gc[0, 1], Gc[1, 0], Gc[1, 1] = G00, G01, G01, G11
        # cov2d = T S T^T: dS = T^T Gc T, dT = 2 Gc T S
        GT = np.empty((2, 3))
        for r in range(2):
            for k in range(3):
                GT[r, k] = Gc[r, 0] * T[0, k] + Gc[r, 1] * T[1, k]
        dS = np.empty((3, 3))
        for r in range(3):
            for k in range(3):
                dS[r, k] = T[0, r] * GT[0, k] + T[1, r] * GT[1, k]
        dT = np.empty((2, 3))
        for r in range(2):
            for k in range(3):
                dT[r, k] = 2.0 * (Gc[r, 0] * TS[0, k] + Gc[r, 1] * TS[1, k])
        # T = J V[:3, :3]
        dj00 = dT[0, 0] * V[0, 0] + dT[0, 1] * V[0, 1] + dT[0, 2] * V[0, 2]
        dj02 = dT[0, 0] * V[2, 0] + dT[0, 1] * V[2, 1] + dT[0, 2] * V[2, 2]
        dj11 = dT[1, 0] * V[1, 0] + dT[1, 1] * V[1, 1] + dT[1, 2] * V[1, 2]
        dj12 = dT[1, 0] * V[2, 0] + dT[1, 1] * V[2, 1] + dT[1, 2] * V[2, 2]
        z2, z3 = zs * zs, zs * zs * zs
        dz = -dj00 * fx / z2 + dj02 * 2.0 * fx * tx / z3 - dj11 * fy / z2 + dj12 * 2.0 * fy * ty / z3
        dtx, dty = -dj02 * fx / z2, -dj12 * fy / z2
        dpx, dpy = 0.0, 0.0
        if x_cl:
            dz += dtx * tx / zs
        else:
            dpx += dtx
        if y_cl:
            dz += dty * ty / zs
        else:
            dpy += dty
        gm0, gm1 = g_m[i, 0], g_m[i, 1]
        dpx += gm0 * fx / zs
        dpy += gm1 * fy / zs
        dz += -gm0 * fx * px / z2 - gm1 * fy * py / z2
        for k in range(3):
            g_means[i, k] = V[0, k] * dpx + V[1, k] * dpy + V[2, k] * dz
        # S = M M^T, M = Rq diag(s)
        dR = np.empty((3, 3))
        for r in range(3):
            for k in range(3):
                dM = 2.0 * (dS[r, 0] * M[0, k] + dS[r, 1] * M[1, k] + dS[r, 2] * M[2, k])
                dR[r, k] = dM * scales[i, k]
                if r == 0:
                    g_scales[i, k] = 0.0
                g_scales[i, k] += dM * Rq[r, k]
        w, x, y, z, n = _unit_quat(quats[i])
        if n == 0.0:
            for k in range(4):
                g_quats[i, k] = 0.0
            continue
        dw = 2 * (-z * dR[0, 1] + y * dR[0, 2] + z * dR[1, 0] - x * dR[1, 2] - y * dR[2, 0] + x * dR[2, 1])
        dx = 2 * (
            y * dR[0, 1]
            + z * dR[0, 2]
            + y * dR[1, 0]
            - 2 * x * dR[1, 1]
            - w * dR[1, 2]
            + z * dR[2, 0]
            + w * dR[2, 1]
            - 2 * x * dR[2, 2]
        )
        dy = 2 * (
            -2 * y * dR[0, 0]
            + x * dR[0, 1]
            + w * dR[0, 2]
            + x * dR[1, 0]
            + z * dR[1, 2]
            - w * dR[2, 0]
            + z * dR[2, 1]
            - 2 * y * dR[2, 2]
        )
        dzq = 2 * (
            -2 * z * dR[0, 0]
            - w * dR[0, 1]
            + x * dR[0, 2]
            + w * dR[1, 0]
            - 2 * z * dR[1, 1]
            + y * dR[1, 2]
            + x * dR[2, 0]
            + y * dR[2, 1]
        )
        dot = w * dw + x * dx + y * dy + z * dzq
        g_quats[i, 0] = (dw - w * dot) / n
        g_quats[i, 1] = (dx - x * dot) / n
        g_quats[i, 2] = (dy - y * dot) / n
        g_quats[i, 3] = (dzq - z * dot) / n


def _np64(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to("cpu", torch.float64).numpy())


def _camera(K: torch.Tensor, width: int, height: int) -> np.ndarray:
    """fx, fy, cx, cy and the clamp limits of x/z, y/z (1.3x the field of view), as the reference."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    return np.array(
        [
            fx,
            fy,
            cx,
            cy,
            (width - cx) / fx + 0.3 * width / fx,
            cx / fx + 0.3 * width / fx,
            (height - cy) / fy + 0.3 * height / fy,
            cy / fy + 0.3 * height / fy,
        ]
    )


class ProjectNumba(torch.autograd.Function):
    """(means, quats, scales, viewmat, K, W, H, near, far) -> means2d, conics, depths, extents, visible."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far):
        args = (_np64(means), _np64(quats), _np64(scales), _np64(viewmat), _camera(K, width, height))
        out = np.empty((means.shape[0], 9))
        _project_forward(*args, width, height, near, far, out)
        visible = out[:, 8] > 0.5
        ctx.state = (args, near, far, visible, means.dtype, quats.dtype, scales.dtype)
        o = torch.from_numpy(out).to(device=means.device, dtype=means.dtype)
        vis = torch.from_numpy(visible).to(means.device)
        depths, extents = o[:, 5].contiguous(), o[:, 6:8].contiguous()
        ctx.mark_non_differentiable(depths, extents, vis)
        return o[:, 0:2].contiguous(), o[:, 2:5].contiguous(), depths, extents, vis

    @staticmethod
    def backward(ctx, g_means2d, g_conics, _g_depths, _g_extents, _g_visible):
        (means, quats, scales, V, cam), near, far, visible, dt_m, dt_q, dt_s = ctx.state
        n = means.shape[0]
        g_m = np.zeros((n, 2)) if g_means2d is None else _np64(g_means2d)
        g_c = np.zeros((n, 3)) if g_conics is None else _np64(g_conics)
        gm, gq, gs = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3))
        _project_backward(means, quats, scales, V, cam, near, far, visible, g_m, g_c, gm, gq, gs)
        dev = (g_means2d if g_means2d is not None else g_conics).device
        return (
            torch.from_numpy(gm).to(dev, dt_m),
            torch.from_numpy(gq).to(dev, dt_q),
            torch.from_numpy(gs).to(dev, dt_s),
            None,
            None,
            None,
            None,
            None,
            None,
        )


def project_gaussians_numba(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
) -> Projected:
    """Same arguments and outputs as `project_gaussians` (CPU tensors; viewmat and K get no gradient)."""
    m2, con, depths, ext, vis = ProjectNumba.apply(
        means, quats, scales, viewmat, K, int(width), int(height), float(near), float(far)
    )
    return Projected(means2d=m2, conics=con, depths=depths, extents=ext, visible=vis)
