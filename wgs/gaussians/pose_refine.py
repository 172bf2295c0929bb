"""Training cameras corrected while the model trains (InstantSplat, CF-3DGS).

Structure-from-motion on 4 photos leaves each camera a degree or two off. A model trained at such
cameras bends to fit photos that disagree. `CameraCorrections` gives each training camera a small
rotation and shift, trained by Adam on the same loss as the model; the first camera keeps its
pose, so the world stays where structure-from-motion put it (the scale is held by the other
cameras' photos). The corrections move the Gaussians, not the camera (`localise.move_world`).
"""

from __future__ import annotations

import torch

from .localise import camera_delta, move_world


class CameraCorrections:
    """A rotation omega [n, 3] (axis-angle, radians) and shift tau [n, 3] (normalised-world
    units, in the camera's frame) per training view; view 0's stay zero."""

    def __init__(self, n_views: int, lr: float, device: torch.device):
        self.omega = torch.zeros(n_views, 3, device=device, requires_grad=True)
        self.tau = torch.zeros(n_views, 3, device=device, requires_grad=True)
        self.opt = torch.optim.Adam([self.omega, self.tau], lr=lr)

    def move(
        self, i: int, means: torch.Tensor, quats: torch.Tensor, viewmat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussians [N, 3], [N, 4] as view `i`'s corrected camera sees them at `viewmat`."""
        if i == 0:
            return means, quats
        return move_world(means, quats, viewmat, self.omega[i], self.tau[i])

    def step(self) -> None:
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)

    def deltas(self) -> torch.Tensor:
        """Each view's correction [n, 4, 4] (CPU, float64), applied as delta @ viewmat."""
        omega, tau = self.omega.detach().cpu().double(), self.tau.detach().cpu().double()
        return torch.stack([camera_delta(w, t) for w, t in zip(omega, tau, strict=True)])

    def viewmats(self, viewmats: list[torch.Tensor]) -> list[torch.Tensor]:
        """The corrected world-to-camera matrices [4, 4] of the views, in their own dtype (CPU)."""
        return [(d.to(v.dtype) @ v.cpu()) for d, v in zip(self.deltas(), viewmats, strict=True)]

    def state_dict(self) -> dict:
        return {"omega": self.omega.detach().cpu(), "tau": self.tau.detach().cpu(), "opt": self.opt.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            self.omega.copy_(state["omega"])
            self.tau.copy_(state["tau"])
        self.opt.load_state_dict(state["opt"])


__all__ = ["CameraCorrections"]
