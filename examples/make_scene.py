"""Generate a small synthetic object scene in the Blender (NeRF-Synthetic) format.

The object (a few textured ellipsoids, different per seed) is ray-cast analytically, not by the
Gaussian rasterizer, so it is an independent reference. RGBA images: alpha is the object mask.
With `--room` the object stands in a room instead (a striped table under it, a patterned wall
around it, each view lit differently): RGB photos without masks, the true masks in `true_masks/`
(what automatic masking is measured against). With `--close-up` the training photos are taken
from one side and so close that the object runs out of every one of them (a front-facing capture
like DTU's), while the test views stand back and see all of it. `--kind` picks another object
(round: vase, bottle; boxy: box, cabinet; thin parts: mug, table), `--sphere` spreads the test
views over the whole sphere.

    python examples/make_scene.py OUT_DIR [--seed S] [--size PX] [--train 4] [--test 16] [--room] [--close-up]
                                  [--kind K] [--sphere]
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
        p["R"] = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
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
    c = o[0] ** 2 + o[1] ** 2 - WALL_RADIUS**2
    t_wall = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / np.maximum(2 * a, 1e-9)
    q = o + t_wall[..., None] * d
    ang = np.arctan2(q[..., 1], q[..., 0])
    blobs = np.sin(7 * ang + rng.uniform(0, 6)) * np.sin(2.5 * q[..., 2] + rng.uniform(0, 6)) > 0.55
    wall = np.where(blobs[..., None], np.array([0.85, 0.35, 0.45]), np.array([0.93, 0.9, 0.82]))
    floor = np.array([0.5, 0.5, 0.52])
    out[:] = np.where((q[..., 2] > TABLE_Z - 2.0)[..., None], wall, floor)
    out[on_table] = wood[on_table]
    return out


def hit_ellipsoids(parts: list[dict], o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest ellipsoid along each ray [..., 3] from `o`: (distance [...], inf where none;
    albedo [..., 3]; unit normal [..., 3])."""
    t_best = np.full(d.shape[:-1], np.inf)
    albedo, normal = np.zeros(d.shape), np.zeros(d.shape)
    for p in parts:
        # Ray in the ellipsoid's unit-sphere frame.
        po = ((o - p["c"]) @ p["R"]) / p["r"]
        pd = (d @ p["R"]) / p["r"]
        a = (pd * pd).sum(-1)
        b = 2 * (pd * po).sum(-1)
        c = (po * po).sum() - 1
        disc = b * b - 4 * a * c
        t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
        t = np.where(t > 0, t, np.inf)
        closer = t < t_best
        if not closer.any():
            continue
        local = po + np.where(np.isfinite(t), t, 0.0)[..., None] * pd  # on the unit sphere where hit
        n = (local / p["r"]) @ p["R"].T
        theta = np.arctan2(local[..., 1], local[..., 0])
        phi = np.arccos(np.clip(local[..., 2], -1, 1))
        pattern = (np.sin(p["freq"] * theta) * np.sin(p["freq"] * phi) > 0)[..., None]
        albedo = np.where(closer[..., None], np.where(pattern, p["col"][0], p["col"][1]), albedo)
        normal = np.where(closer[..., None], n / np.linalg.norm(n, axis=-1, keepdims=True), normal)
        t_best = np.where(closer, t, t_best)
    return t_best, albedo, normal


def render(obj, c2w: np.ndarray, size: int, ss: int = 2, background: np.random.Generator | None = None) -> np.ndarray:
    """Ray-cast [size, size, 4] straight-alpha RGBA of `obj` (ellipsoids from `make_object`, or a
    `ShapeObject`), supersampled ss x ss (premultiplied average); with a `background` generator,
    opaque RGBA of the object in the room (`room`) under a light of random strength and tint."""
    n = size * ss
    f = 0.5 * n / math.tan(0.5 * FOV_X)
    ij = (np.arange(n) + 0.5 - n / 2) / f
    x, y = np.meshgrid(ij, ij)
    d_cam = np.stack([x, -y, -np.ones_like(x)], -1)  # OpenGL camera looks down -z
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    t_best, albedo, normal = obj.hit(o, d) if isinstance(obj, ShapeObject) else hit_ellipsoids(obj, o, d)
    light = np.array([0.4, 0.3, 0.85])
    light /= np.linalg.norm(light)
    rgb = albedo * (0.35 + 0.65 * np.clip((normal * light).sum(-1), 0, 1)[..., None])
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


# Objects of a known kind, for measuring shape (round ones, boxy ones, ones with thin parts): signed
# distance functions, sphere-traced. Each stands upright (+z) at the origin, turned about z at random.
def sd_box(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


def sd_revolution(p: np.ndarray, radius, half_height: float, slope: float) -> np.ndarray:
    """A solid of revolution about z: radius(z) for |z| < half_height; `slope` bounds |radius'| (the
    distance is scaled by it so that sphere tracing never oversteps)."""
    rho = np.linalg.norm(p[..., :2], axis=-1)
    side = (rho - radius(p[..., 2])) / math.sqrt(1 + slope * slope)
    return np.maximum(side, np.abs(p[..., 2]) - half_height)


def sd_torus_y(p: np.ndarray, centre: np.ndarray, major: float, minor: float) -> np.ndarray:
    """A torus in the xz plane (its axis along y)."""
    q = p - centre
    return np.hypot(np.hypot(q[..., 0], q[..., 2]) - major, q[..., 1]) - minor


class ShapeObject:
    """A solid given by its signed distance `sdf(points [..., 3]) -> [...]`, two colours striped
    across it, turned about z by `turn` radians."""

    def __init__(self, sdf, colours: np.ndarray, turn: float, stripes: float):
        self.sdf, self.colours, self.stripes = sdf, colours, stripes
        c, s = math.cos(turn), math.sin(turn)
        self.R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # object -> world

    def local_sdf(self, p: np.ndarray) -> np.ndarray:
        return self.sdf(p @ self.R)

    def hit(
        self, o: np.ndarray, d: np.ndarray, steps: int = 160, far: float = 8.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sphere tracing: as `hit_ellipsoids`."""
        t = np.zeros(d.shape[:-1])
        hit = np.zeros(d.shape[:-1], dtype=bool)
        for _ in range(steps):
            dist = self.local_sdf(o + t[..., None] * d)
            hit |= dist < 1e-4
            t = np.where(hit, t, t + np.maximum(dist, 1e-4))
            if (hit | (t > far)).all():
                break
        p = o + t[..., None] * d
        eps = 1e-4
        normal = np.stack([self.local_sdf(p + eps * e) - self.local_sdf(p - eps * e) for e in np.eye(3)], -1)
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        local = p @ self.R
        around = np.arctan2(local[..., 1], local[..., 0])
        band = np.sin(self.stripes * local[..., 2]) * np.sin(self.stripes * around) > 0
        albedo = np.where(band[..., None], self.colours[0], self.colours[1])
        return np.where(hit, t, np.inf), albedo, normal


def vase(rng: np.random.Generator):
    """Round: a vase whose radius swells and narrows along its height."""
    base, swell, freq, phase = rng.uniform(0.32, 0.42), rng.uniform(0.1, 0.18), rng.uniform(2.0, 3.5), rng.uniform(0, 3)
    return lambda p: sd_revolution(p, lambda z: base + swell * np.sin(freq * z + phase), 0.75, swell * freq)


def bottle(rng: np.random.Generator):
    """Round: a bottle, a wide body and a narrow neck joined by a smooth shoulder."""
    body, neck, shoulder = rng.uniform(0.35, 0.45), rng.uniform(0.1, 0.16), rng.uniform(0.0, 0.25)

    def radius(z):
        s = np.clip((z - shoulder) / 0.3, 0, 1)
        return body + (neck - body) * s * s * (3 - 2 * s)

    return lambda p: sd_revolution(p, radius, 0.8, 1.6 * (body - neck) / 0.3)


def box(rng: np.random.Generator):
    """Boxy: a box."""
    half = rng.uniform([0.3, 0.2, 0.3], [0.55, 0.45, 0.6])
    return lambda p: sd_box(p, half)


def cabinet(rng: np.random.Generator):
    """Boxy: a wide box with a narrower one on top."""
    low, high = rng.uniform([0.45, 0.3, 0.25], [0.6, 0.4, 0.35]), rng.uniform([0.2, 0.15, 0.2], [0.35, 0.25, 0.3])
    lift = np.array([0.0, 0.0, low[2] + high[2]]) - np.array([0.0, 0.0, 0.3])
    return lambda p: np.minimum(sd_box(p - np.array([0.0, 0.0, -0.3]), low), sd_box(p - lift, high))


def mug(rng: np.random.Generator):
    """Thin part: a cylindrical mug with a ring handle."""
    r, h, ring = rng.uniform(0.35, 0.45), rng.uniform(0.4, 0.55), rng.uniform(0.045, 0.07)
    handle = np.array([r + 0.12, 0.0, 0.0])
    return lambda p: np.minimum(
        sd_revolution(p, lambda z: np.full_like(z, r), h, 0.0), sd_torus_y(p, handle, 0.25, ring)
    )


def table(rng: np.random.Generator):
    """Thin parts: a table top on four thin legs."""
    top = rng.uniform([0.5, 0.35, 0.04], [0.7, 0.5, 0.07])
    leg = rng.uniform(0.035, 0.06)
    corners = [np.array([sx * (top[0] - 0.1), sy * (top[1] - 0.1), -0.2]) for sx in (-1, 1) for sy in (-1, 1)]

    def sdf(p):
        d = sd_box(p - np.array([0.0, 0.0, 0.4]), top)
        for c in corners:
            d = np.minimum(d, sd_box(p - c, np.array([leg, leg, 0.6])))
        return d

    return sdf


KINDS = {"blobs": None, "vase": vase, "bottle": bottle, "box": box, "cabinet": cabinet, "mug": mug, "table": table}


def make_shape(kind: str, rng: np.random.Generator):
    """The object of a kind (`KINDS`): ellipsoids for "blobs", else a `ShapeObject`."""
    if kind == "blobs":
        return make_object(rng)
    return ShapeObject(
        KINDS[kind](rng), rng.uniform(0.15, 0.95, (2, 3)), rng.uniform(0, 2 * math.pi), float(rng.integers(4, 9))
    )


CLOSE_UP_DISTANCE = 2.0  # training cameras of --close-up: the object (about 1.1 across its centre) overfills them
CLOSE_UP_ARC = math.radians(180.0)  # ... within this arc of azimuths, all from one side
STAND_BACK_DISTANCE = 3.6  # test cameras of --close-up, which see the whole object


def sphere_positions(n: int, radius: float = RADIUS) -> list[np.ndarray]:
    """n camera positions spread evenly over the whole sphere (a Fibonacci lattice)."""
    out = []
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        az = math.pi * (1 + math.sqrt(5.0)) * i
        out.append(radius * np.array([math.sqrt(1 - z * z) * math.cos(az), math.sqrt(1 - z * z) * math.sin(az), z]))
    return out


def camera_positions(
    n: int, rng: np.random.Generator, train: bool, close_up: bool = False, sphere: bool = False
) -> list[np.ndarray]:
    """Training views go around the object from above; test views around it at -10..50 degrees of
    elevation, or over the whole sphere with `sphere`."""
    if sphere and not train:
        return sphere_positions(n)
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


def make_scene(
    out: Path,
    seed: int = 0,
    size: int = 128,
    n_train: int = 4,
    n_test: int = 16,
    room: bool = False,
    close_up: bool = False,
    kind: str = "blobs",
    sphere: bool = False,
) -> Path:
    rng = np.random.default_rng(seed)
    parts = make_shape(kind, rng)
    out.mkdir(parents=True, exist_ok=True)
    for split, n in (("train", n_train), ("test", n_test)):
        frames = []
        for i, eye in enumerate(camera_positions(n, rng, split == "train", close_up, sphere)):
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
    ap.add_argument(
        "--close-up",
        action="store_true",
        help="training photos from one side, so close that the object runs out of every one",
    )
    ap.add_argument(
        "--kind",
        choices=tuple(KINDS),
        default="blobs",
        help="the object: textured ellipsoids, or a round, boxy or thin-parted solid",
    )
    ap.add_argument("--sphere", action="store_true", help="test views spread over the whole sphere")
    a = ap.parse_args()
    make_scene(a.out, a.seed, a.size, a.train, a.test, a.room, a.close_up, a.kind, a.sphere)
    print(f"wrote {a.out} (seed {a.seed}, {a.size}x{a.size}, {a.train} train + {a.test} test views)")


if __name__ == "__main__":
    main()
