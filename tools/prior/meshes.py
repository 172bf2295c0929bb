"""Triangle meshes for the corpus: one flat Mesh type and its loaders (glTF/GLB with or without
Draco compression, OBJ with MTL textures). World convention of the corpus: z up, object centred
at the origin and scaled into the unit sphere (`normalise`)."""

from __future__ import annotations

import base64
import io
import json
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from wgs.errors import InputError


@dataclass
class Mesh:
    """vertices [V, 3], faces [F, 3] int, per-face base colour [F, 3] in [0, 1]; optional texture
    coordinates uv [V, 2] with per-face texture index (-1: none) into `textures` ([h, w, 3] float);
    optional triplanar texture (procedural detail on untextured surfaces)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_colors: np.ndarray
    uv: np.ndarray | None = None
    face_texture: np.ndarray | None = None
    textures: list[np.ndarray] = field(default_factory=list)
    triplanar: np.ndarray | None = None
    triplanar_scale: float = 1.0

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, np.float64)
        self.faces = np.asarray(self.faces, np.int64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(
                f"vertices [V, 3] and faces [F, 3] expected, got {self.vertices.shape}, {self.faces.shape}"
            )
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise ValueError("face indices out of range")
        if self.face_texture is None:
            self.face_texture = np.full(len(self.faces), -1, np.int64)

    @property
    def face_normals(self) -> np.ndarray:
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-20)


def concat(meshes: list[Mesh]) -> Mesh:
    """One mesh from several (texture indices renumbered; uv zero where a part has none)."""
    if not meshes:
        raise ValueError("no meshes to join")
    verts, faces, cols, uvs, ftex = [], [], [], [], []
    texs: list[np.ndarray] = []
    off = 0
    for m in meshes:
        verts.append(m.vertices)
        faces.append(m.faces + off)
        cols.append(m.face_colors)
        uvs.append(m.uv if m.uv is not None else np.zeros((len(m.vertices), 2)))
        assert m.face_texture is not None  # filled in __post_init__
        ftex.append(np.where(m.face_texture >= 0, m.face_texture + len(texs), -1))
        texs.extend(m.textures)
        off += len(m.vertices)
    any_uv = any(m.uv is not None for m in meshes)
    return Mesh(
        np.concatenate(verts),
        np.concatenate(faces),
        np.concatenate(cols),
        np.concatenate(uvs) if any_uv else None,
        np.concatenate(ftex),
        texs,
    )


def normalise(mesh: Mesh, radius: float = 1.0) -> Mesh:
    """Centre the bounding box at the origin and scale the farthest vertex to `radius`."""
    used = mesh.vertices[np.unique(mesh.faces)] if len(mesh.faces) else mesh.vertices
    centre = (used.min(0) + used.max(0)) / 2
    r = np.linalg.norm(used - centre, axis=1).max()
    if not np.isfinite(r) or r <= 0:
        raise ValueError("degenerate mesh (no extent)")
    return replace(mesh, vertices=(mesh.vertices - centre) * (radius / r))


def y_up_to_z_up(mesh: Mesh) -> Mesh:
    """glTF and most OBJ files are y-up; the corpus world is z-up (NeRF-Synthetic's)."""
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return replace(mesh, vertices=mesh.vertices @ R.T)


# ----------------------------------------------------------------------------- images
def decode_image(data: bytes, where: str | Path) -> np.ndarray:
    """PNG/JPEG bytes -> float [h, w, 3] (alpha dropped)."""
    from PIL import Image

    try:
        img = Image.open(io.BytesIO(data)).convert("RGB")
    except Exception as exc:  # PIL raises many types for damaged files
        raise InputError(f"cannot decode texture ({exc})", where) from None
    img.thumbnail((512, 512))
    return np.asarray(img, np.float32) / 255.0


# ----------------------------------------------------------------------------- glTF
_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _read_glb(path: Path) -> tuple[dict, bytes | None]:
    data = path.read_bytes()
    if len(data) < 20 or data[:4] != b"glTF":
        raise InputError("not a GLB file", path)
    (json_len,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20 : 20 + json_len])
    rest = 20 + json_len
    binary = None
    if rest + 8 <= len(data):
        (bin_len,) = struct.unpack_from("<I", data, rest)
        binary = data[rest + 8 : rest + 8 + bin_len]
    return doc, binary


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = R * np.asarray(node.get("scale", [1, 1, 1]), np.float64)
    m[:3, 3] = node.get("translation", [0, 0, 0])
    return m


def load_gltf(path: str | Path) -> Mesh:
    """A .gltf (buffers as files or data URIs) or .glb scene, flattened into one Mesh in y-up
    glTF coordinates; KHR_draco_mesh_compression primitives are decoded with DracoPy."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".glb":
            doc, glb_bin = _read_glb(path)
        else:
            doc, glb_bin = json.loads(path.read_text(encoding="utf-8")), None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read glTF ({exc})", path) from None

    def uri_bytes(uri: str) -> bytes:
        if uri.startswith("data:"):
            return base64.b64decode(uri.split(",", 1)[1])
        target = (path.parent / uri).resolve()
        if not target.is_file():
            raise InputError(f"missing file {uri} (not in the snapshot?)", path)
        return target.read_bytes()

    buffers = [glb_bin if "uri" not in b else uri_bytes(b["uri"]) for b in doc.get("buffers", [])]

    def view_bytes(i: int) -> bytes:
        bv = doc["bufferViews"][i]
        off = bv.get("byteOffset", 0)
        return buffers[bv["buffer"]][off : off + bv["byteLength"]]

    def accessor(i: int) -> np.ndarray:
        a = doc["accessors"][i]
        dtype, n = np.dtype(_COMPONENT[a["componentType"]]), _NCOMP[a["type"]]
        if "bufferView" not in a:
            return np.zeros((a["count"], n))
        bv = doc["bufferViews"][a["bufferView"]]
        buf = buffers[bv["buffer"]]
        start = bv.get("byteOffset", 0) + a.get("byteOffset", 0)
        stride = bv.get("byteStride") or dtype.itemsize * n
        arr = np.ndarray((a["count"], n), dtype, buf, start, (stride, dtype.itemsize))
        out = arr.astype(np.float64)
        if a.get("normalized") and dtype.kind in "iu":
            out /= np.iinfo(dtype.type).max
        return out

    image_cache: dict[int, np.ndarray | None] = {}

    def image(i: int) -> np.ndarray | None:
        """The decoded image, or None when the snapshot lacks its file (the base colour remains)."""
        if i not in image_cache:
            img = doc["images"][i]
            try:
                data = view_bytes(img["bufferView"]) if "bufferView" in img else uri_bytes(img["uri"])
            except InputError:
                data = None
            image_cache[i] = None if data is None else decode_image(data, path)
        return image_cache[i]

    parts: list[Mesh] = []

    def primitive(prim: dict, world: np.ndarray) -> Mesh | None:
        if prim.get("mode", 4) != 4:
            return None
        draco = prim.get("extensions", {}).get("KHR_draco_mesh_compression")
        uv = None
        colors = None
        if draco is not None:
            import DracoPy

            dm = DracoPy.decode(view_bytes(draco["bufferView"]))
            pos = np.asarray(dm.points, np.float64).reshape(-1, 3)
            faces = np.asarray(dm.faces, np.int64).reshape(-1, 3)
            if "TEXCOORD_0" in draco["attributes"] and dm.tex_coord is not None and len(dm.tex_coord):
                uv = np.asarray(dm.tex_coord, np.float64).reshape(-1, 2)
        else:
            attrs = prim["attributes"]
            pos = accessor(attrs["POSITION"])
            faces = (
                accessor(prim["indices"]).astype(np.int64).reshape(-1, 3)
                if "indices" in prim
                else np.arange(len(pos) - len(pos) % 3).reshape(-1, 3)
            )
            if "TEXCOORD_0" in attrs:
                uv = accessor(attrs["TEXCOORD_0"])
            if "COLOR_0" in attrs:
                colors = accessor(attrs["COLOR_0"])[:, :3]
        pos = pos @ world[:3, :3].T + world[:3, 3]
        mat = doc["materials"][prim["material"]] if "material" in prim else {}
        pbr = mat.get("pbrMetallicRoughness", {})
        base = np.clip(np.asarray(pbr.get("baseColorFactor", [0.8, 0.8, 0.8, 1]), np.float64)[:3], 0, 1)
        fcol = np.tile(base, (len(faces), 1))
        if colors is not None and len(faces):
            fcol = fcol * colors[faces].mean(1)
        textures, ftex = [], None
        tex_info = pbr.get("baseColorTexture")
        if tex_info is not None and uv is not None:
            src = doc["textures"][tex_info["index"]].get("source")
            tex = image(src) if src is not None else None
            if tex is not None:
                textures = [tex]
                ftex = np.zeros(len(faces), np.int64)
        return Mesh(pos, faces, fcol, uv if textures else None, ftex, textures)

    def visit(node_id: int, parent: np.ndarray) -> None:
        node = doc["nodes"][node_id]
        world = parent @ _node_matrix(node)
        if "mesh" in node:
            for prim in doc["meshes"][node["mesh"]]["primitives"]:
                m = primitive(prim, world)
                if m is not None and len(m.faces):
                    parts.append(m)
        for c in node.get("children", []):
            visit(c, world)

    scenes = doc.get("scenes") or [{"nodes": list(range(len(doc.get("nodes", []))))}]
    try:
        for n in scenes[doc.get("scene", 0)].get("nodes", []):
            visit(n, np.eye(4))
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise InputError(f"malformed glTF ({type(exc).__name__}: {exc})", path) from None
    if not parts:
        raise InputError("no triangles in the glTF scene", path)
    return concat(parts)


# ----------------------------------------------------------------------------- OBJ
def load_obj(path: str | Path) -> Mesh:
    """An OBJ (with its MTL and diffuse texture when present) through trimesh, in file coordinates."""
    import trimesh

    path = Path(path)
    try:
        loaded: Any = trimesh.load(str(path), force="mesh", process=False)  # a Trimesh (force="mesh")
    except Exception as exc:  # trimesh raises many types for damaged files
        raise InputError(f"cannot read OBJ ({type(exc).__name__}: {exc})", path) from None
    if not hasattr(loaded, "faces") or len(loaded.faces) == 0:
        raise InputError("no triangles in the OBJ file", path)
    faces = np.asarray(loaded.faces, np.int64)
    visual = loaded.visual
    fcol = np.full((len(faces), 3), 0.8)
    uv, ftex, textures = None, None, []
    if getattr(visual, "kind", None) == "texture" and getattr(visual, "uv", None) is not None:
        material = visual.material
        img = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if img is not None:
            textures = [np.asarray(img.convert("RGB"), np.float32) / 255.0]
            uv = np.asarray(visual.uv, np.float64).copy()
            uv[:, 1] = 1.0 - uv[:, 1]  # OBJ's v points up; the sampler's down (glTF's)
            ftex = np.zeros(len(faces), np.int64)
        else:
            diffuse = getattr(material, "diffuse", None)
            if diffuse is not None:
                fcol[:] = np.asarray(diffuse, np.float64)[:3] / 255.0
    elif getattr(visual, "kind", None) in ("vertex", "face"):
        fcol = np.asarray(visual.face_colors, np.float64)[:, :3] / 255.0
    return Mesh(np.asarray(loaded.vertices, np.float64), faces, fcol, uv, ftex, textures)


def load_mesh(path: str | Path) -> Mesh:
    path = Path(path)
    with open(path, "rb") as fh:
        if fh.read(40).startswith(b"version https://git-lfs"):
            raise InputError("a Git LFS pointer, not a mesh (the snapshot lacks LFS content)", path)
    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb"):
        return load_gltf(path)
    if suffix == ".obj":
        return load_obj(path)
    raise InputError(f"unknown mesh format {suffix!r} (glTF, GLB, OBJ)", path)
