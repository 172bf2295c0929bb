"""A folder of unposed photos made by our own renderer: a textured object seen from a ring of
cameras, RGB on a plain background, masks beside, the true cameras returned for comparison."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from tools.prior.meshes import concat
from tools.prior.procedural import _palette, fractal_noise, superquadric
from tools.prior.raster import render_rgba
from wgs.io.images import read_image, write_png
from wgs.scene.orbit import look_at


def make_photos(
    out: Path,
    n: int = 16,
    width: int = 320,
    height: int = 240,
    seed: int = 0,
    radius: float = 2.4,
    masks: bool = True,
    layout: str = "images",
    turntable: bool = False,
    azimuths: list[float] | None = None,
    shape_seed: int | None = None,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Write `n` photos (`out/images/` or, with layout="flat", `out/`) and `out/masks/`, on a ring
    (or at `azimuths`, degrees); returns {name: (K [3, 3], w2c [4, 4])}. `shape_seed`: another
    object (its parts' sizes and places drawn from it)."""
    rng = np.random.default_rng(seed)
    parts = []
    placed = [
        ((0.7, 0.5, 0.45), (0, 0, 0)),
        ((0.3, 0.3, 0.35), (0.35, 0.2, 0.55)),
        ((0.25, 0.4, 0.2), (-0.45, -0.3, 0.3)),
    ]
    if shape_seed is not None:
        other = np.random.default_rng(shape_seed)
        placed = [(tuple(other.uniform(0.15, 0.6, 3)), tuple(other.uniform(-0.5, 0.5, 3))) for _ in range(4)]
    for size, offset in placed:
        m = superquadric(np.array(size), 0.6, 0.7, nu=24, nv=48)
        m.vertices = m.vertices + np.array(offset)
        m.face_colors = rng.uniform(0.1, 1.0, (len(m.faces), 3))  # a unique pattern: features match once
        parts.append(m)
    mesh = concat(parts)
    mesh.triplanar = _palette(rng, fractal_noise(rng, 256, octaves=6), 5)
    mesh.triplanar_scale = 0.7
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    image_dir = out / "images" if layout == "images" else out
    cams = {}
    # turntable: the object turns, the room stays put in every photo (features there lie)
    bg = rng.uniform(0, 1, (height // 4, width // 4, 3)).repeat(4, 0).repeat(4, 1) if turntable else 0.45
    for i in range(n):
        az = np.radians(azimuths[i]) if azimuths is not None else 2 * np.pi * i / n
        el = np.deg2rad(25 + 10 * np.sin(3 * az))
        eye = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        w2c = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        rgba = render_rgba(mesh, w2c, K, width, height)
        a = rgba[..., 3:]
        name = f"photo_{i:03d}.png"
        write_png(image_dir / name, rgba[..., :3] * a + bg * (1 - a))
        if masks:
            write_png(out / "masks" / name, rgba[..., 3])
        cams[name] = (K, w2c)
    return cams


DIAGONAL_35MM = 43.27  # mm, COLMAP's full frame diagonal: EXIF's focal = f35 / 43.27 x the photo's diagonal


def as_exif_jpegs(folder: Path, focal_px: float) -> float:
    """The photos of `folder/images` rewritten as JPEGs (the masks keep their stems) whose EXIF
    gives the 35 mm equivalent focal length in whole millimetres, as a camera writes it (so a per
    cent or two off `focal_px`); returns the focal length in pixels that EXIF then gives."""
    given = None
    for png in sorted((folder / "images").glob("*.png")):
        rgb = read_image(png)[..., :3]
        h, w = rgb.shape[:2]
        f35 = round(focal_px / math.hypot(w, h) * DIAGONAL_35MM)
        jpg = png.with_suffix(".jpg")
        spec = oiio.ImageSpec(w, h, 3, oiio.UINT8)
        spec.attribute("Exif:FocalLengthIn35mmFilm", f35)
        spec.attribute("Compression", "jpeg:95")
        out = oiio.ImageOutput.create(str(jpg))
        out.open(str(jpg), spec)
        out.write_image(np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8))
        out.close()
        png.unlink()
        given = given or f35 / DIAGONAL_35MM * math.hypot(w, h)
    return float(given)
