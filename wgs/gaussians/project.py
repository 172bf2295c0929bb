"""EWA projection of 3D Gaussians to 2D (pure torch, differentiable, device-agnostic).

Math follows 3DGS / gsplat: cov2d = J W Σ Wᵀ Jᵀ + 0.3·I (low-pass dilation), the Jacobian evaluated
at the mean with x/z, y/z clamped to 1.3x the field of view so off-screen Gaussians stay bounded.
Computed in float64 internally: anisotropy up to 1e6 makes det(cov2d) cancel badly in float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

BLUR = 0.3  # px², 3DGS's screen-space dilation
SIGMA_CUT = 3.0  # footprint extent in standard deviations


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities. Shapes: [N, 2], [N, 3], [N], [N, 2], [N]."""

    means2d: torch.Tensor  # pixel coordinates (pixel centres at +0.5)
    conics: torch.Tensor  # inverse 2D covariance (a, b, c) of [[a, b], [b, c]]
    depths: torch.Tensor  # camera-space z
    extents: torch.Tensor  # half-size of the 3-sigma bounding box in px (x, y); 0 when culled
    visible: torch.Tensor  # bool


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] wxyz (any norm; zero falls back to identity) -> [N, 3, 3]."""
    norm = quats.norm(dim=-1, keepdim=True)
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    q = torch.where(norm > 1e-12, quats / norm.clamp_min(1e-12), ident)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quats.shape[:-1], 3, 3)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """A rotation [3, 3] -> unit quaternion wxyz [4] (Shepperd's method, stable at every angle)."""
    m = R.double()
    t = m.trace()
    cands = torch.stack([1 + t, 1 + 2 * m[0, 0] - t, 1 + 2 * m[1, 1] - t, 1 + 2 * m[2, 2] - t])
    i = int(cands.argmax())
    r = cands[i].clamp_min(1e-12).sqrt()
    if i == 0:
        q = [r, (m[2, 1] - m[1, 2]) / r, (m[0, 2] - m[2, 0]) / r, (m[1, 0] - m[0, 1]) / r]
    elif i == 1:
        q = [(m[2, 1] - m[1, 2]) / r, r, (m[0, 1] + m[1, 0]) / r, (m[0, 2] + m[2, 0]) / r]
    elif i == 2:
        q = [(m[0, 2] - m[2, 0]) / r, (m[0, 1] + m[1, 0]) / r, r, (m[1, 2] + m[2, 1]) / r]
    else:
        q = [(m[1, 0] - m[0, 1]) / r, (m[0, 2] + m[2, 0]) / r, (m[1, 2] + m[2, 1]) / r, r]
    quat = torch.stack(q) / 2
    return quat * torch.sign(quat[0]) if quat[0] != 0 else quat


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions [..., 4] (rotation a after b)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def covariance3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Σ = R S Sᵀ Rᵀ: [N, 4], [N, 3] -> [N, 3, 3]."""
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def project_gaussians(
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
    """Project N Gaussians into one pinhole camera.

    Args:
        means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (activated), viewmat [4, 4] world-to-camera
        (OpenCV), K [3, 3]. Gaussians with depth outside (near, far) or with a degenerate 2D
        covariance are culled (visible = False, extents = 0).
    """
    out_dtype = means.dtype
    f64 = torch.float64
    means, quats, scales = means.to(f64), quats.to(f64), scales.to(f64)
    viewmat, K = viewmat.to(f64), K.to(f64)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    z = p[:, 2]
    valid = (z > near) & (z < far)
    zs = torch.where(valid, z, torch.ones_like(z))  # keeps culled rows finite
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * width / fx, cx / fx + 0.3 * width / fx
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * height / fy, cy / fy + 0.3 * height / fy
    tx = zs * torch.minimum(torch.maximum(p[:, 0] / zs, -lim_xn), lim_xp)
    ty = zs * torch.minimum(torch.maximum(p[:, 1] / zs, -lim_yn), lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2], -1).reshape(-1, 2, 3)
    cov_c = R @ covariance3d(quats, scales) @ R.T
    cov2d = J @ cov_c @ J.transpose(-1, -2)
    a = cov2d[:, 0, 0] + BLUR
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + BLUR
    det = a * c - b * b
    valid = valid & (det > 0) & torch.isfinite(det)
    det_s = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    means2d = torch.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], -1)
    ext = SIGMA_CUT * torch.stack([a, c], -1).clamp_min(0).sqrt()
    # off-screen: the 3-sigma box misses the image
    on = (
        (means2d[:, 0] + ext[:, 0] > 0)
        & (means2d[:, 0] - ext[:, 0] < width)
        & (means2d[:, 1] + ext[:, 1] > 0)
        & (means2d[:, 1] - ext[:, 1] < height)
    )
    valid = valid & on & torch.isfinite(means2d).all(-1)
    vf = valid[:, None]
    return Projected(
        means2d=torch.where(vf, means2d, torch.zeros_like(means2d)).to(out_dtype),
        conics=torch.where(vf, conics, torch.zeros_like(conics)).to(out_dtype),
        depths=z.detach().to(out_dtype),
        extents=torch.where(vf, ext, torch.zeros_like(ext)).detach().to(out_dtype),
        visible=valid,
    )
