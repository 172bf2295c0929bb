"""Localising a camera on a frozen model: the pose at which the model fits a photo best.

Photos posed by structure-from-motion from a few views carry pose errors of a degree or two, and
a novel view scored at a camera that far off loses several dB that say nothing about the model.
Pose-free methods (InstantSplat, CF-3DGS) therefore score a test photo at its camera refined on
the frozen model; `localise` is that refinement. The model does not move.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ..scene.dataset import Frame, composite
from .project import quat_multiply, quat_to_rotmat
from .render import rasterize
from .splats import Splats, activate


def axis_angle_quat(omega: torch.Tensor) -> torch.Tensor:
    """Axis-angle [3] (radians) -> unit quaternion [4] wxyz; smooth through 0 (sinc, not a division)."""
    theta = torch.sqrt((omega * omega).sum() + 1e-12)
    return torch.cat([torch.cos(theta / 2)[None], 0.5 * torch.sinc(theta / (2 * torch.pi)) * omega])


def move_world(
    means: torch.Tensor, quats: torch.Tensor, viewmat: torch.Tensor, omega: torch.Tensor, tau: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussians moved so that they render at `viewmat` as the unmoved ones do at the camera
    `camera_delta(omega, tau) @ viewmat`: a world point x goes to Rc^T (R(omega) (Rc x + tc) + tau - tc).
    The rasterizer gives gradients for the Gaussians, not the camera; this carries them to the
    camera's correction.

    Args:
        means [N, 3], quats [N, 4] wxyz (unit); viewmat [4, 4] world-to-camera;
        omega [3] axis-angle (radians) and tau [3], in the camera's frame.
    Returns:
        moved means [N, 3] and quats [N, 4].
    """
    Rc, tc = viewmat[:3, :3], viewmat[:3, 3]
    R = quat_to_rotmat(axis_angle_quat(omega)[None])[0]
    moved = ((means @ Rc.T + tc) @ R.T + tau - tc) @ Rc
    return moved, quat_multiply(axis_angle_quat(Rc.T @ omega).expand_as(quats), quats)


def camera_delta(omega: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """The camera-frame correction [4, 4] = [R(omega) | tau] (detached), applied as delta @ viewmat."""
    with torch.no_grad():
        delta = torch.eye(4, dtype=omega.dtype)
        delta[:3, :3] = quat_to_rotmat(axis_angle_quat(omega)[None])[0]
        delta[:3, 3] = tau
    return delta


def localise(
    splats: Splats, frame: Frame, background: torch.Tensor, steps: int, lr: float = 2e-3
) -> tuple[Frame, torch.Tensor]:
    """`frame` with its camera moved (6 degrees of freedom, Adam on the photometric L1 of the photo
    composited on `background`) to where the frozen `splats` fit its photo best.

    The world moves instead of the camera (`move_world`).

    Args:
        splats: a model (raw parameters, as trained); detached here.
        frame: a camera with its photo (and mask, where it has one); CPU tensors.
        background [3]; steps: Adam steps (0: the frame unchanged); lr: Adam's step size (radians
            and normalised-world units).
    Returns:
        the moved frame, and delta [4, 4] (camera-frame rotation and shift; identity at steps=0).
    """
    means, quats, scales, opac, sh = (t.detach().cpu() for t in activate(splats))
    truth = composite(frame.pixels, frame.mask, background)
    omega = torch.zeros(3, requires_grad=True)
    tau = torch.zeros(3, requires_grad=True)
    opt = torch.optim.Adam([omega, tau], lr=lr)
    for _ in range(steps):
        moved, q = move_world(means, quats, frame.viewmat, omega, tau)
        rgb, _, _ = rasterize(moved, q, scales, opac, sh, frame.viewmat, frame.K, frame.width, frame.height, background)
        loss = (rgb - truth).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    delta = camera_delta(omega, tau)
    return replace(frame, viewmat=delta @ frame.viewmat), delta


__all__ = ["axis_angle_quat", "camera_delta", "localise", "move_world"]
