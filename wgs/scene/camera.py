"""The camera, one convention for the package: world-to-camera OpenCV [4, 4] (x right, y down,
z forward) and intrinsics K [3, 3] with pixel centres at +0.5 (COLMAP's), at working resolution."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch


def camera_center(w2c):
    """Camera centre -R^T t in world coordinates [3] of a world-to-camera [4, 4] (numpy or torch)."""
    return -w2c[:3, :3].T @ w2c[:3, 3]


@dataclass
class Camera:
    """A pinhole camera. K [3, 3], viewmat [4, 4] world-to-camera (OpenCV), float32 tensors."""

    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int

    @property
    def center(self) -> torch.Tensor:
        return camera_center(self.viewmat)

    def to_json(self) -> dict[str, Any]:
        return {"K": self.K.tolist(), "viewmat": self.viewmat.tolist(), "width": self.width, "height": self.height}

    @staticmethod
    def from_json(d: dict[str, Any]) -> Camera:
        return Camera(
            torch.tensor(d["K"], dtype=torch.float32),
            torch.tensor(d["viewmat"], dtype=torch.float32),
            int(d["width"]),
            int(d["height"]),
        )
