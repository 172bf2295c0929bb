"""Generate a small synthetic object scene in the Blender (NeRF-Synthetic) format.

The object (a few textured ellipsoids, different per seed) is ray-cast analytically, not by the
Gaussian rasterizer, so it is an independent reference. RGBA images: alpha is the object mask.
With `--room` the object stands in a room instead (a striped table under it, a patterned wall
around it, each view lit differently): RGB photos without masks, the true masks in `true_masks/`
(what automatic masking is measured against). With `--close-up` the training photos are taken
from one side and so close that the object runs out of every one of them (a front-facing capture
like DTU's), while the test views stand back and see all of it.

    python examples/make_scene.py OUT_DIR [--seed S] [--size PX] [--train 4] [--test 16] [--room] [--close-up]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from wgs.io.images import write_png  # noqa: E402

FOV_X = 0.6911112070083618  # NeRF-Synthetic's camera_angle_x
RADIUS = 3.0


def make_object(rng: np.random.Generator) -> list[dict]:
    """A body plus 3-4 attached parts: ellipsoids with centre, radii, rotation and two colours."""
    parts = [{"c": np.zeros(3), "r": rng.uniform(0.55, 0.75, 3)}]
    for _ in range(int(rng.integers(3, 5))):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        parts.append({"c": d * rng.uniform(0.45, 0.7), "r": rng.uniform(0.18, 0.4, 3)})
    for p in parts:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        p["R"] = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                           [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                           [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        p["col"] = rng.uniform(0.15, 0.95, (2, 3))
        p["freq"] = float(rng.integers(3, 9))
    return parts


def look_at_c2w(eye: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world looking at the origin (+z up in the world)."""
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    if np.linalg.norm(right) < 1e-6:
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


TABLE_Z = -1.0  # the table's top, under the object (room scenes)
WALL_RADIUS = 6.0  # a cylindrical wall around the table (room scenes)


def room(o: np.ndarray, d: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """What the rays [..., 3] from `o` see of the room: a wood-striped table top (z = TABLE_Z, |x|,
    |y| < 2.5), else a wall of flowers-like blobs on a pale ground, else a grey floor."""
    out = np.empty(d.shape)
    t_tab = np.where(d[..., 2] < -1e-6, (TABLE_Z - o[2]) / np.minimum(d[..., 2], -1e-6), np.inf)
    p = o + np.where(np.isfinite(t_tab), t_tab, 0.0)[..., None] * d
    on_table = np.isfinite(t_tab) & (np.abs(p[..., 0]) < 2.5) & (np.abs(p[..., 1]) < 2.5)
    grain = 0.5 + 0.5 * np.sin(9.0 * p[..., 0] + 2.0 * np.sin(3.0 * p[..., 1]))
    wood = np.array([0.45, 0.28, 0.14]) + grain[..., None] * np.array([0.25, 0.17, 0.08])
    # the wall: the cylinder x² + y² = R² hit from inside
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = 2 * (o[0] * d[..., 0] + o[1] * d[..., 1])
    c = o[0] ** 2 + o[1] ** 2 - WALL_RADIUS ** 2
    t_wall = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / np.maximum(2 * a, 1e-9)
    q = o + t_wall[..., None] * d
    ang = np.arctan2(q[..., 1], q[..., 0])
    blobs = np.sin(7 * ang + rng.uniform(0, 6)) * np.sin(2.5 * q[..., 2] + rng.uniform(0, 6)) > 0.55
    wall = np.where(blobs[..., None], np.array([0.85, 0.35, 0.45]), np.array([0.93, 0.9, 0.82]))
    floor = np.array([0.5, 0.5, 0.52])
    out[:] = np.where((q[..., 2] > TABLE_Z - 2.0)[..., None], wall, floor)
    out[on_table] = wood[on_table]
    return out


def render(parts: list[dict], c2w: np.ndarray, size: int, ss: int = 2, background: np.random.Generator | None = None
           ) -> np.ndarray:
    """Ray-cast [size, size, 4] straight-alpha RGBA, supersampled ss x ss (premultiplied average);
    with a `background` generator, opaque RGBA of the object in the room (`room`) under a light of
    random strength and tint."""
    n = size * ss
    f = 0.5 * n / math.tan(0.5 * FOV_X)
    ij = (np.arange(n) + 0.5 - n / 2) / f
    x, y = np.meshgrid(ij, ij)
    d_cam = np.stack([x, -y, -np.ones_like(x)], -1)  # OpenGL camera looks down -z
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    t_best = np.full((n, n), np.inf)
    rgb = np.zeros((n, n, 3))
    light = np.array([0.4, 0.3, 0.85])
    light /= np.linalg.norm(light)
    for p in parts:
        # Ray in the ellipsoid's unit-sphere frame.
        po = ((o - p["c"]) @ p["R"]) / p["r"]
        pd = (d @ p["R"]) / p["r"]
        a = (pd * pd).sum(-1)
        b = 2 * (pd * po).sum(-1)
        c = (po * po).sum() - 1
        disc = b * b - 4 * a * c
        hit = disc > 0
        t = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < t_best
        if not closer.any():
            continue
        local = po + np.where(np.isfinite(t), t, 0.0)[..., None] * pd  # on the unit sphere where hit
        normal = (local / p["r"]) @ p["R"].T
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        theta = np.arctan2(local[..., 1], local[..., 0])
        phi = np.arccos(np.clip(local[..., 2], -1, 1))
        pattern = (np.sin(p["freq"] * theta) * np.sin(p["freq"] * phi) > 0)[..., None]
        albedo = np.where(pattern, p["col"][0], p["col"][1])
        shade = 0.35 + 0.65 * np.clip((normal * light).sum(-1), 0, 1)[..., None]
        rgb = np.where(closer[..., None], albedo * shade, rgb)
        t_best = np.where(closer, t, t_best)
    alpha = np.isfinite(t_best).astype(np.float64)
    if background is not None:
        light = background.uniform(0.7, 1.15) * background.uniform(0.85, 1.0, 3)
        rgb = np.clip(np.where(alpha[..., None] > 0, rgb, room(o, d, background)) * light, 0, 1)
        rgb = rgb.reshape(size, ss, size, ss, 3).mean(axis=(1, 3))
        return np.concatenate([rgb, alpha.reshape(size, ss, size, ss).mean(axis=(1, 3))[..., None]], -1)
    rgba = np.concatenate([rgb * alpha[..., None], alpha[..., None]], -1)
    rgba = rgba.reshape(size, ss, size, ss, 4).mean(axis=(1, 3))
    a = rgba[..., 3:]
    rgba[..., :3] = np.where(a > 0, rgba[..., :3] / np.maximum(a, 1e-8), 0.0)
    return rgba


CLOSE_UP_DISTANCE = 2.0  # training cameras of --close-up: the object (about 1.1 across its centre) overfills them
CLOSE_UP_ARC = math.radians(180.0)  # ... within this arc of azimuths, all from one side
STAND_BACK_DISTANCE = 3.6  # test cameras of --close-up, which see the whole object


def camera_positions(n: int, rng: np.random.Generator, train: bool, close_up: bool = False) -> list[np.ndarray]:
    out = []
    for i in range(n):
        if close_up:  # front-facing: azimuths spread over one arc, the test views a little wider
            span = CLOSE_UP_ARC * (1.0 if train else 1.4)
            az = span * (i / max(n - 1, 1) - 0.5) + (rng.uniform(-0.1, 0.1) if train else 0.0)
        else:
            az = 2 * math.pi * (i / n) + (rng.uniform(-0.2, 0.2) if train else 0.37)
        el = math.radians(rng.uniform(15, 45) if train else -10 + 60 * ((i * 7) % n) / max(n - 1, 1))
        radius = (CLOSE_UP_DISTANCE if train else STAND_BACK_DISTANCE) if close_up else RADIUS
        out.append(radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))
    return out


def make_scene(out: Path, seed: int = 0, size: int = 128, n_train: int = 4, n_test: int = 16,
               room: bool = False, close_up: bool = False) -> Path:
    rng = np.random.default_rng(seed)
    parts = make_object(rng)
    out.mkdir(parents=True, exist_ok=True)
    for split, n in (("train", n_train), ("test", n_test)):
        frames = []
        for i, eye in enumerate(camera_positions(n, rng, split == "train", close_up)):
            c2w = look_at_c2w(eye)
            img = render(parts, c2w, size, background=rng if room else None).astype(np.float32)
            if room:  # a photo without a mask, and the true mask apart
                write_png(out / "true_masks" / f"r_{i}_{split}.png", img[..., 3])
                img = img[..., :3]
            write_png(out / split / f"r_{i}.png", img)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV_X, "frames": frames}, indent=2))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--train", type=int, default=4)
    ap.add_argument("--test", type=int, default=16)
    ap.add_argument("--room", action="store_true", help="the object in a room, photos without masks")
    ap.add_argument("--close-up", action="store_true",
                    help="training photos from one side, so close that the object runs out of every one")
    a = ap.parse_args()
    make_scene(a.out, a.seed, a.size, a.train, a.test, a.room, a.close_up)
    print(f"wrote {a.out} (seed {a.seed}, {a.size}x{a.size}, {a.train} train + {a.test} test views)")


if __name__ == "__main__":
    main()
