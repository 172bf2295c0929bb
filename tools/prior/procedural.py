"""Procedural corpus material: shapes (unions of superquadrics and tori; kit-bashed assemblies of
boxes and cylinders) and textures (fractal noise, stripes, checkers, crops of the natural
photographs that ship inside matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .meshes import Mesh, concat


def _spow(x: np.ndarray, e: float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** e


def _grid_faces(nu: int, nv: int, wrap_v: bool) -> np.ndarray:
    faces = []
    cols = nv if wrap_v else nv - 1
    for i in range(nu - 1):
        for j in range(cols):
            a, b = i * nv + j, i * nv + (j + 1) % nv
            c, d = a + nv, b + nv
            faces += [(a, b, d), (a, d, c)]
    return np.asarray(faces, np.int64)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def superquadric(radii: np.ndarray, e1: float, e2: float, nu: int = 20, nv: int = 40) -> Mesh:
    """Closed superquadric surface (poles included) with exponents e1 (latitude), e2 (longitude)."""
    u = np.linspace(-np.pi / 2, np.pi / 2, nu)[:, None]
    v = np.linspace(-np.pi, np.pi, nv, endpoint=False)[None]
    x = radii[0] * _spow(np.cos(u), e1) * _spow(np.cos(v), e2)
    y = radii[1] * _spow(np.cos(u), e1) * _spow(np.sin(v), e2)
    z = radii[2] * _spow(np.sin(u), e1) * np.ones_like(v)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = _grid_faces(nu, nv, True)
    return Mesh(verts, faces, np.full((len(faces), 3), 0.8))


def torus(major: float, minor: float, nu: int = 16, nv: int = 40) -> Mesh:
    u = np.linspace(0, 2 * np.pi, nu)[:, None]
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)[None]
    x = (major + minor * np.cos(u)) * np.cos(v)
    y = (major + minor * np.cos(u)) * np.sin(v)
    z = minor * np.sin(u) * np.ones_like(v)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = _grid_faces(nu, nv, True)
    return Mesh(verts, faces, np.full((len(faces), 3), 0.8))


def random_shape(rng: np.random.Generator) -> Mesh:
    """A body and 1-4 attached parts, each with its own colour."""
    parts = []
    for k in range(int(rng.integers(2, 6))):
        if k > 0 and rng.random() < 0.2:
            m = torus(rng.uniform(0.2, 0.45), rng.uniform(0.04, 0.12))
        else:
            size = rng.uniform(0.35, 0.7, 3) if k == 0 else rng.uniform(0.08, 0.4, 3)
            m = superquadric(size, rng.uniform(0.2, 1.6), rng.uniform(0.2, 1.6))
        R = random_rotation(rng)
        offset = np.zeros(3) if k == 0 else rng.normal(size=3) / np.sqrt(3) * rng.uniform(0.3, 0.7)
        m.vertices = m.vertices @ R.T + offset
        m.face_colors = np.tile(rng.uniform(0.05, 0.95, 3), (len(m.faces), 1))
        parts.append(m)
    return concat(parts)


def box(size: np.ndarray) -> Mesh:
    """Axis-aligned box centred at the origin, 12 outward-facing triangles."""
    corners = (np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * size / 2).astype(float)
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return Mesh(corners, faces, np.full((12, 3), 0.8))


def cylinder(radius: float, height: float, sides: int = 16) -> Mesh:
    """Closed cylinder along z centred at the origin."""
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], -1)
    verts = np.concatenate(
        [
            np.c_[ring, np.full(sides, -height / 2)],
            np.c_[ring, np.full(sides, height / 2)],
            [[0, 0, -height / 2], [0, 0, height / 2]],
        ]
    )
    faces = []
    for i in range(sides):
        j = (i + 1) % sides
        faces += [
            (i, j, sides + j),
            (i, sides + j, sides + i),  # side
            (2 * sides, j, i),
            (2 * sides + 1, sides + i, sides + j),
        ]  # bottom and top caps
    return Mesh(verts, np.asarray(faces), np.full((len(faces), 3), 0.8))


def kitbash_shape(rng: np.random.Generator) -> Mesh:
    """A construction-toy-like assembly: a body box and 12-48 beams, plates, axles, wheels and studs
    glued to it, mostly axis-aligned, in a palette of 2-4 flat colours. Thin parts, gaps and
    concavities are what a 4-view model renders fat and smeared."""
    palette = rng.uniform(0.03, 0.97, (int(rng.integers(2, 5)), 3))
    palette[0] = rng.uniform(0.05, 0.3) * np.ones(3)  # dark grey parts, as such toys have
    body = rng.uniform(0.3, 0.8, 3)
    parts = [box(body)]
    parts[0].face_colors[:] = palette[int(rng.integers(len(palette)))]
    for _ in range(int(rng.integers(12, 49))):
        kind = rng.choice(["beam", "plate", "axle", "wheel", "stud"], p=[0.3, 0.25, 0.15, 0.1, 0.2])
        if kind == "beam":
            size = np.sort(rng.uniform(0.04, 0.12, 3))
            size[2] = rng.uniform(0.3, 0.9)
            m = box(rng.permutation(size))
        elif kind == "plate":
            size = rng.uniform(0.15, 0.5, 3)
            size[int(rng.integers(3))] = rng.uniform(0.02, 0.06)
            m = box(size)
        elif kind == "axle":
            m = cylinder(rng.uniform(0.015, 0.04), rng.uniform(0.3, 0.9), 8)
        elif kind == "wheel":
            m = cylinder(rng.uniform(0.1, 0.25), rng.uniform(0.05, 0.15), 20)
        else:
            m = cylinder(rng.uniform(0.02, 0.04), rng.uniform(0.02, 0.04), 10)
        if rng.random() < 0.8:  # axis-aligned: one of the 3 axes becomes the part's z
            m.vertices = np.roll(m.vertices, int(rng.integers(3)), axis=1)
        else:
            m.vertices = m.vertices @ random_rotation(rng).T
        # glued onto the body's surface or sticking out of it
        anchor = rng.uniform(-0.5, 0.5, 3) * body
        face = int(rng.integers(3))
        anchor[face] = np.sign(rng.uniform(-1, 1)) * body[face] / 2 * rng.uniform(0.9, 1.6)
        m.vertices = m.vertices + anchor
        m.face_colors = np.tile(palette[int(rng.integers(len(palette)))], (len(m.faces), 1))
        parts.append(m)
    return concat(parts)


# ----------------------------------------------------------------------------- textures
def _upsample(grid: np.ndarray, size: int) -> np.ndarray:
    g = grid.shape[0]
    x = np.linspace(0, g - 1, size, endpoint=False)
    i0 = np.floor(x).astype(int)
    f = x - i0
    i1 = (i0 + 1) % g
    rows = grid[i0] * (1 - f)[:, None] + grid[i1] * f[:, None]
    return rows[:, i0] * (1 - f)[None] + rows[:, i1] * f[None]


def fractal_noise(rng: np.random.Generator, size: int = 256, octaves: int = 5) -> np.ndarray:
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        out += amp * _upsample(rng.random((2 ** (o + 2), 2 ** (o + 2))), size)
        total += amp
        amp *= rng.uniform(0.45, 0.7)
    out /= total
    return (out - out.min()) / max(np.ptp(out), 1e-9)


def _palette(rng: np.random.Generator, t: np.ndarray, n: int) -> np.ndarray:
    cols = rng.uniform(0.03, 0.97, (n, 3))
    pos = np.linspace(0, 1, n)
    return np.stack([np.interp(t, pos, cols[:, c]) for c in range(3)], -1)


def natural_images() -> list[Path]:
    """Photographs inside the installed matplotlib package (no download)."""
    import matplotlib

    d = Path(matplotlib.get_data_path()) / "sample_data"
    return [p for p in (d / "grace_hopper.jpg", d / "Minduka_Present_Blue_Pack.png") if p.is_file()]


def random_texture(rng: np.random.Generator, size: int = 256) -> tuple[np.ndarray, str]:
    """[size, size, 3] in [0, 1] and its kind."""
    kind = rng.choice(["noise", "stripes", "checker", "photo", "noise-stripes"], p=[0.35, 0.2, 0.15, 0.15, 0.15])
    yy, xx = np.mgrid[0:size, 0:size] / size
    if kind == "photo" and natural_images():
        from .meshes import decode_image

        paths = natural_images()
        path = paths[int(rng.integers(len(paths)))]
        img = decode_image(path.read_bytes(), path)
        c = int(min(img.shape[:2]) * rng.uniform(0.3, 0.9))
        y0 = int(rng.integers(0, img.shape[0] - c + 1))
        x0 = int(rng.integers(0, img.shape[1] - c + 1))
        crop = img[y0 : y0 + c, x0 : x0 + c]
        idx = np.arange(size) * c // size
        return crop[idx][:, idx].astype(np.float64), "photo"
    if kind == "photo":
        kind = "noise"
    if kind == "noise":
        return _palette(rng, fractal_noise(rng, size), int(rng.integers(2, 5))), kind
    angle = rng.uniform(0, np.pi)
    freq = int(rng.integers(2, 12))
    u = xx * np.cos(angle) + yy * np.sin(angle)
    if kind == "checker":
        t = ((np.floor(xx * freq) + np.floor(yy * freq)) % 2).astype(float)
    else:
        t = 0.5 + 0.5 * np.sin(2 * np.pi * freq * u)
        if kind == "noise-stripes":
            t = np.clip(t + 0.6 * (fractal_noise(rng, size) - 0.5), 0, 1)
    return _palette(rng, t, 2), kind
