"""A small CPU mesh renderer for the corpus: z-buffer triangle rasterizer (numba) -> shader (numpy).

Cameras follow the house convention (world-to-camera OpenCV 4x4 + K). The rasterizer writes, per
pixel, the nearest triangle and its perspective-correct barycentrics; the shader interpolates
texture coordinates and lights the surface with view-independent Lambert light (so a 3DGS can fit
the views exactly). Supersampling gives anti-aliased edges; alpha is the coverage (the mask).
"""

from __future__ import annotations

import numba
import numpy as np

from wgs.scene.camera import camera_center

from .meshes import Mesh

NEAR = 1e-3
LIGHTS = np.array([[0.4, -0.5, 0.75], [-0.6, 0.3, 0.4]])  # world directions (z up), normalised below
LIGHT_POWER = np.array([0.65, 0.3])
AMBIENT = 0.35


@numba.njit(cache=True)
def _zbuffer(px, py, pz, faces, height, width, tri, bary, depth):  # pragma: no cover - numba
    for f in range(faces.shape[0]):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        z0, z1, z2 = pz[i0], pz[i1], pz[i2]
        if z0 <= NEAR or z1 <= NEAR or z2 <= NEAR:
            continue
        x0, y0, x1, y1, x2, y2 = px[i0], py[i0], px[i1], py[i1], px[i2], py[i2]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        xmin = max(int(np.floor(min(x0, x1, x2))), 0)
        xmax = min(int(np.ceil(max(x0, x1, x2))), width - 1)
        ymin = max(int(np.floor(min(y0, y1, y2))), 0)
        ymax = min(int(np.ceil(max(y0, y1, y2))), height - 1)
        for y in range(ymin, ymax + 1):
            sy = y + 0.5
            for x in range(xmin, xmax + 1):
                sx = x + 0.5
                w0 = ((x1 - sx) * (y2 - sy) - (x2 - sx) * (y1 - sy)) / area
                w1 = ((x2 - sx) * (y0 - sy) - (x0 - sx) * (y2 - sy)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                iz = w0 / z0 + w1 / z1 + w2 / z2
                z = 1.0 / iz
                if z < depth[y, x]:
                    depth[y, x] = z
                    tri[y, x] = f
                    bary[y, x, 0] = w0 / z0 * z
                    bary[y, x, 1] = w1 / z1 * z


def rasterize(
    vertices: np.ndarray, faces: np.ndarray, viewmat: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """vertices [V, 3], faces [F, 3] -> triangle id [H, W] (-1: empty), barycentrics [H, W, 3], depth [H, W]."""
    cam = vertices @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    zs = np.where(z > NEAR, z, 1.0)
    px = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    py = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    tri = np.full((height, width), -1, np.int64)
    bary = np.zeros((height, width, 3))
    depth = np.full((height, width), np.inf)
    _zbuffer(px, py, z, faces.astype(np.int64), height, width, tri, bary, depth)
    bary[..., 2] = 1.0 - bary[..., 0] - bary[..., 1]
    return tri, bary, depth


def sample_bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """tex [h, w, 3], uv [N, 2] (glTF: v down from the top, wrapping) -> [N, 3]."""
    h, w = tex.shape[:2]
    x = (uv[:, 0] % 1.0) * w - 0.5
    y = (uv[:, 1] % 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, x1, y0, y1 = x0 % w, (x0 + 1) % w, y0 % h, (y0 + 1) % h
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def shade(mesh: Mesh, tri: np.ndarray, bary: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Colour [H, W, 3] of the covered pixels (0 elsewhere): base colour x texture x Lambert light."""
    out = np.zeros((*tri.shape, 3))
    hit = tri >= 0
    f = tri[hit]
    b = bary[hit]
    corners = mesh.faces[f]  # [N, 3]
    pos = np.einsum("nk,nkc->nc", b, mesh.vertices[corners])
    colour = mesh.face_colors[f].astype(np.float64)
    if mesh.uv is not None and mesh.textures and mesh.face_texture is not None:
        uv = np.einsum("nk,nkc->nc", b, mesh.uv[corners])
        for t, tex in enumerate(mesh.textures):
            sel = mesh.face_texture[f] == t
            if sel.any():
                colour[sel] *= sample_bilinear(tex, uv[sel])
    if mesh.triplanar is not None:
        colour *= triplanar(mesh.triplanar, pos, mesh.face_normals[f], mesh.triplanar_scale)
    n = mesh.face_normals[f]
    n = np.where(((eye - pos) * n).sum(-1, keepdims=True) < 0, -n, n)  # two-sided
    lights = LIGHTS / np.linalg.norm(LIGHTS, axis=1, keepdims=True)
    light = AMBIENT + (np.clip(n @ lights.T, 0, None) * LIGHT_POWER).sum(-1)
    out[hit] = np.clip(colour * light[:, None], 0, 1)
    return out


def triplanar(tex: np.ndarray, pos: np.ndarray, normal: np.ndarray, scale: float) -> np.ndarray:
    """A texture projected along the three axes, blended by the normal's components."""
    wts = np.abs(normal) ** 4
    wts /= wts.sum(-1, keepdims=True).clip(1e-12)
    p = pos * scale
    return (
        sample_bilinear(tex, p[:, [1, 2]]) * wts[:, :1]
        + sample_bilinear(tex, p[:, [0, 2]]) * wts[:, 1:2]
        + sample_bilinear(tex, p[:, [0, 1]]) * wts[:, 2:]
    )


def render_rgba(
    mesh: Mesh, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, supersample: int = 2
) -> np.ndarray:
    """Straight-alpha RGBA [H, W, 4] in [0, 1]; alpha = pixel coverage by the object."""
    s = supersample
    Ks = K.copy()
    Ks[:2] *= s
    tri, bary, _ = rasterize(mesh.vertices, mesh.faces, viewmat, Ks, width * s, height * s)
    eye = camera_center(viewmat)
    rgb = shade(mesh, tri, bary, eye)
    cov = (tri >= 0).astype(np.float64)
    premult = (rgb * cov[..., None]).reshape(height, s, width, s, 3).mean((1, 3))
    alpha = cov.reshape(height, s, width, s).mean((1, 3))
    straight = premult / np.clip(alpha, 1e-8, None)[..., None]
    return np.concatenate([np.clip(straight, 0, 1), alpha[..., None]], -1).astype(np.float32)
