"""Mirror images of views: for an object symmetric about a plane, the photo of a camera flipped
left-right is the photo its reflection across the plane would take. The reflection turns the
world's handedness, and the flip turns it back, so the mirrored camera is an ordinary camera
(`mirror_frame`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch


@dataclass
class MirrorPlane:
    """The plane normal . x = offset (normalised world)."""

    normal: torch.Tensor  # [3], unit length
    offset: float

    def to_json(self) -> dict:
        return {"normal": [round(float(v), 6) for v in self.normal], "offset": round(self.offset, 6)}

    @staticmethod
    def from_json(d: dict) -> MirrorPlane:
        return MirrorPlane(torch.tensor(d["normal"], dtype=torch.float32), float(d["offset"]))


def reflect(points: torch.Tensor, normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """points [N, 3] mirrored across B planes (normals [B, 3] unit, offsets [B]) -> [B, N, 3]."""
    dist = points @ normals.T - offsets  # [N, B]
    return points[None] - 2.0 * dist.T[..., None] * normals[:, None, :]


MIRROR_SUFFIX = ".mirror"


def mirror_name(name: str) -> str:
    """train_r_0.png -> train_r_0.mirror.png"""
    stem, dot, ext = name.rpartition(".")
    return f"{stem}{MIRROR_SUFFIX}.{ext}" if dot else name + MIRROR_SUFFIX


def mirror_frame(frame, plane: MirrorPlane, shows_colour: bool = True):
    """The view of `frame`'s camera reflected across the plane, its image and mask flipped left-right
    (`shows_colour`: whether training may use the flipped image's colours, or its mask only).

    A world point x at pixel (u, v) of the frame is at (W - u, v) of the result, reflected: the
    world-to-camera becomes F [R | t] M (M the reflection, F = diag(-1, 1, 1) in the camera), and
    the principal point moves to W - cx."""
    n = plane.normal.to(frame.viewmat)
    M = torch.eye(4, dtype=frame.viewmat.dtype)
    M[:3, :3] -= 2.0 * torch.outer(n, n)
    M[:3, 3] = 2.0 * plane.offset * n
    F = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=frame.viewmat.dtype))
    K = frame.K.clone()
    K[0, 2] = frame.width - K[0, 2]
    flip = lambda t: t.flip(1).contiguous() if t is not None else None  # noqa: E731
    return replace(
        frame,
        K=K,
        viewmat=F @ frame.viewmat @ M,
        name=mirror_name(frame.name),
        image=flip(frame.image),
        mask=flip(frame.mask),
        shows_colour=shows_colour,
    )
