"""Camera paths from the training cameras only: an orbit fitted to them, and novel viewpoints
between neighbouring training views (GaussianObject draws 30-70% of the arc between neighbours).
Test cameras never enter here, so nothing before evaluation depends on them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .dataset import Frame


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera (OpenCV: x right, y down, z forward) looking from eye at target."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


@dataclass
class Orbit:
    """Up axis, height along it and radius around it of the training cameras (object at the origin)."""

    up: np.ndarray
    height: float
    radius: float
    e1: np.ndarray
    e2: np.ndarray

    def point(self, angle: float, height: float | None = None, radius: float | None = None) -> np.ndarray:
        h = self.height if height is None else height
        r = self.radius if radius is None else radius
        return self.up * h + r * (math.cos(angle) * self.e1 + math.sin(angle) * self.e2)

    def angle_of(self, p: np.ndarray) -> float:
        return math.atan2(float(p @ self.e2), float(p @ self.e1))


def fit_orbit(train: list[Frame]) -> Orbit:
    centers = np.stack([f.center.double().numpy() for f in train])
    up = np.stack([-f.viewmat[1, :3].double().numpy() for f in train]).mean(0)  # camera -y is up
    up /= max(np.linalg.norm(up), 1e-12)
    height = float((centers @ up).mean())
    radius = float(np.linalg.norm(centers - np.outer(centers @ up, up), axis=1).mean())
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return Orbit(up, height, radius, e1, np.cross(up, e1))


def orbit_frames(train: list[Frame], n: int) -> list[Frame]:
    """n cameras evenly on the orbit, looking at the object centre, with the first camera's K."""
    orb = fit_orbit(train)
    f0 = train[0]
    out = []
    for i in range(n):
        w2c = look_at(orb.point(2 * math.pi * i / n), np.zeros(3), orb.up)
        out.append(
            Frame(f0.K.clone(), torch.tensor(w2c, dtype=torch.float32), f0.width, f0.height, name=f"path_{i:03d}.png")
        )
    return out


def novel_views(
    train: list[Frame], per_pair: int, lo: float = 0.3, hi: float = 0.7, seed: int = 0
) -> list[tuple[Frame, float]]:
    """Viewpoints between azimuthally neighbouring training cameras.

    For each neighbour pair (sorted by angle on the fitted orbit, wrapping around), `per_pair`
    poses at random fractions in [lo, hi] of the arc, interpolating angle, height and distance,
    looking at the object centre with the nearer camera's intrinsics. Returns (frame, distance to
    the nearest training camera centre).
    """
    orb = fit_orbit(train)
    rng = np.random.default_rng(seed)
    centers = [f.center.double().numpy() for f in train]
    angles = [orb.angle_of(c) for c in centers]
    order = sorted(range(len(train)), key=lambda i: angles[i])
    out = []
    for j, a in enumerate(order):
        b = order[(j + 1) % len(order)]
        if a == b:
            continue
        da = (angles[b] - angles[a]) % (2 * math.pi)
        ha, hb = float(centers[a] @ orb.up), float(centers[b] @ orb.up)
        ra = float(np.linalg.norm(centers[a] - ha * orb.up))
        rb = float(np.linalg.norm(centers[b] - hb * orb.up))
        for k in range(per_pair):
            s = float(rng.uniform(lo, hi))
            eye = orb.point(angles[a] + s * da, ha + s * (hb - ha), ra + s * (rb - ra))
            near = train[a] if s < 0.5 else train[b]
            w2c = look_at(eye, np.zeros(3), orb.up)
            frame = Frame(
                near.K.clone(),
                torch.tensor(w2c, dtype=torch.float32),
                near.width,
                near.height,
                name=f"novel_{j:02d}_{k:02d}.png",
            )
            dist = min(float(np.linalg.norm(eye - c)) for c in centers)
            out.append((frame, dist))
    return out


def sphere_views(train: list[Frame], n: int, below_deg: float, above_deg: float) -> list[tuple[Frame, float]]:
    """n viewpoints spread evenly (Fibonacci lattice) over a band of the sphere around the object at
    the training cameras' mean distance, from `below_deg` under the lowest training camera to
    `above_deg` over the highest (elevation about the fitted up axis, within -80..85 degrees);
    each looks at the object centre with the nearest training camera's intrinsics. Returns
    (frame, distance to the nearest training camera centre)."""
    orb = fit_orbit(train)
    centers = np.stack([f.center.double().numpy() for f in train])
    dist = float(np.linalg.norm(centers, axis=1).mean())
    elev = np.degrees(np.arcsin(np.clip(centers @ orb.up / np.linalg.norm(centers, axis=1), -1, 1)))
    lo = math.radians(max(-80.0, float(elev.min()) - below_deg))
    hi = math.radians(min(85.0, float(elev.max()) + above_deg))
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = []
    for i in range(n):
        s = math.sin(lo) + (math.sin(hi) - math.sin(lo)) * (i + 0.5) / n  # uniform in area over the band
        c = math.sqrt(max(0.0, 1 - s * s))
        a = golden * i
        eye = dist * (s * orb.up + c * (math.cos(a) * orb.e1 + math.sin(a) * orb.e2))
        d = np.linalg.norm(centers - eye, axis=1)
        near = train[int(d.argmin())]
        w2c = look_at(eye, np.zeros(3), orb.up)
        out.append(
            (
                Frame(
                    near.K.clone(),
                    torch.tensor(w2c, dtype=torch.float32),
                    near.width,
                    near.height,
                    name=f"sphere_{i:03d}.png",
                ),
                float(d.min()),
            )
        )
    return out
