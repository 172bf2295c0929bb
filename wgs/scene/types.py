"""Scene data types. One convention: world-to-camera OpenCV 4x4 (x right, y down, z forward)
plus 3x3 intrinsics K with pixel centres at +0.5 (COLMAP's), float64, at working resolution."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import camera_center


@dataclass
class Distortion:
    """A COLMAP camera model to undistort through pycolmap (None for a pinhole)."""

    model: str  # e.g. "OPENCV", "SIMPLE_RADIAL"
    params: list[float]


@dataclass
class View:
    """One posed image of the source scene.

    Attributes:
        name: unique image name (file name in the source's image folder).
        image: absolute path of the image file.
        K: [3, 3] intrinsics at the image file's resolution.
        w2c: [4, 4] world-to-camera (OpenCV).
        width, height: image file size in pixels.
        mask: absolute path of a separate mask file, or None (alpha channel, or no mask).
        distortion: lens model to undistort with, or None.
    """

    name: str
    image: Path
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    mask: Path | None = None
    distortion: Distortion | None = None

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        return camera_center(self.w2c)

    @property
    def forward(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates, [3]."""
        return self.w2c[2, :3] / np.linalg.norm(self.w2c[2, :3])


@dataclass
class RawScene:
    """A scene as found on disk, before images are loaded.

    `train` and `test` index into `views`; `test` may be empty. `notes` are things the user should
    know (skipped frames, chosen split) and are printed by `wgs prepare`.
    """

    root: Path
    format: str
    views: list[View]
    train: list[int] = field(default_factory=list)
    test: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    metadata_files: list[Path] = field(default_factory=list)  # hashed for freshness
