"""The prior's object corpus: objects from public repository snapshots plus procedural ones, each
rendered into a Blender-format scene (`transforms_{train,test}.json`, RGBA PNGs, alpha = mask)
that `wgs prepare` reads unchanged. Resumable: an object whose `object.json` exists is done.

Evaluation scenes (NeRF-Synthetic, DTU, instant-ngp, GaussianObject) never enter: the sources are
the five repositories below and our own procedural shapes.
"""

from __future__ import annotations

import hashlib
import json
import math
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wgs.errors import InputError
from wgs.io.images import write_png
from wgs.progress import log

from .meshes import Mesh, load_mesh, normalise, y_up_to_z_up
from .procedural import kitbash_shape, random_rotation, random_shape, random_texture
from .raster import render_rgba

FOV_X = 0.6911112070083618  # NeRF-Synthetic's camera_angle_x
RADIUS = 4.0


@dataclass(frozen=True)
class Source:
    repo: str  # owner/name on GitHub
    pattern: str  # glob inside the snapshot
    licence: str  # as the repository states it (per-object details recorded where the repo has them)
    y_up: bool = True


SOURCES = (
    Source(
        "pmndrs/market-assets",
        "files/models/*/model.gltf",
        "per object in info.json (pmndrs market licence id; 1 = CC0)",
    ),
    Source("odedstein/meshes", "objects/*/*.obj", "per object in objects/<name>/README.md (mostly CC-BY/CC0)"),
    Source("alecjacobson/common-3d-test-models", "data/*.obj", "per model, listed in the repository README"),
    # its superquadric_objects/ are Git LFS pointers in the snapshot: our procedural shapes replace them
    Source(
        "eleramp/pybullet-object-models",
        "pybullet_object_models/ycb_objects/*/textured_simple_reoriented.obj",
        "YCB object set (CC-BY 4.0), repository MIT",
        y_up=False,
    ),
    Source(
        "sbtron/glTF-Sample-Models",
        "2.0/{Avocado,BarramundiFish,BoomBox,Corset,Lantern,WaterBottle}/glTF/*.gltf",
        "CC0 (Microsoft), per model README",
    ),
)


def snapshot_dir(mirror: Path, repo: str) -> Path | None:
    """The git directory `fetch` made for owner/name under the mirror folder, if any."""
    base = mirror / repo.replace("/", "+") / "repo"
    for d in (base / ".git", base):
        if (d / "HEAD").is_file() or (d / "objects").is_dir():
            return d
    return None


def extract(git_dir: Path, dest: Path) -> tuple[int, list[str]]:
    """Write the snapshot's newest tree under dest, skipping blobs the snapshot lacks (files of
    4 MiB and more); returns (files written, paths missing)."""
    listing = subprocess.run(
        ["git", "--git-dir", str(git_dir), "ls-tree", "-r", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.splitlines()
    written, missing = 0, []
    for line in listing:
        meta, path = line.split("\t", 1)
        _, kind, sha = meta.split()
        if kind != "blob":
            continue
        target = dest / path
        if target.exists():
            written += 1
            continue
        blob = subprocess.run(["git", "--git-dir", str(git_dir), "cat-file", "blob", sha], capture_output=True)
        if blob.returncode != 0:
            missing.append(path)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(blob.stdout)
        written += 1
    return written, missing


def _expand(pattern: str) -> list[str]:
    if "{" not in pattern:
        return [pattern]
    head, rest = pattern.split("{", 1)
    alts, tail = rest.split("}", 1)
    return [head + a + tail for a in alts.split(",")]


def list_objects(src_root: Path) -> list[dict]:
    """Every corpus object found under the extracted sources, with provenance."""
    out = []
    for s in SOURCES:
        root = src_root / s.repo.replace("/", "+")
        paths = sorted(p for pat in _expand(s.pattern) for p in root.glob(pat))
        for p in paths:
            rel = p.relative_to(root).as_posix()
            licence = s.licence
            info = p.parent / "info.json"
            if info.is_file():
                meta = json.loads(info.read_text(encoding="utf-8"))
                licence = f"pmndrs market licence id {meta.get('license')}, creator {meta.get('creator')}"
            readme = p.parent / "README.md"
            if readme.is_file() and "odedstein" in s.repo:
                lines = [
                    x
                    for x in readme.read_text(encoding="utf-8", errors="replace").splitlines()
                    if "licen" in x.lower() or "cc" in x.lower()
                ]
                licence = (lines[0].strip() if lines else licence)[:200]
            generic = p.stem in ("model", "textured_simple_reoriented")  # named by their folder
            name = f"{s.repo.split('/')[1]}-{p.parent.name if generic else p.stem}"
            out.append(
                {"name": _slug(name), "kind": "mesh", "repo": s.repo, "path": rel, "licence": licence, "y_up": s.y_up}
            )
    return out


def procedural_objects(n: int, first: int = 0, kind: str = "procedural") -> list[dict]:
    return [
        {"name": f"{kind}-{i:04d}", "kind": kind, "seed": i, "licence": "ours (generated)"}
        for i in range(first, first + n)
    ]


def _slug(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "-" for c in s.lower())


def is_holdout(name: str, every: int = 10) -> bool:
    """Objects kept out of the prior's training to measure generalisation (stable by name)."""
    return int(hashlib.sha1(name.encode()).hexdigest(), 16) % every == 0


def interleave(groups: list[list[dict]]) -> list[dict]:
    """Round-robin over the sources so any prefix of the corpus is diverse."""
    out, i = [], 0
    while any(i < len(g) for g in groups):
        out += [g[i] for g in groups if i < len(g)]
        i += 1
    return out


# ----------------------------------------------------------------------------- scenes
def look_at_c2w(eye: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world looking at the origin, z up (Blender's)."""
    back = eye / np.linalg.norm(eye)
    right = np.cross([0.0, 0.0, 1.0], back)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-6 else np.array([1.0, 0.0, 0.0])
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def c2w_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    from wgs.scene.convention import c2w_opengl_to_w2c_opencv

    return c2w_opengl_to_w2c_opencv(c2w)


def sphere_eyes(rng: np.random.Generator, n: int, elev_lo: float, elev_hi: float) -> np.ndarray:
    """n camera centres at RADIUS, azimuth uniform, elevation uniform in sin between the bounds (degrees)."""
    az = rng.uniform(0, 2 * np.pi, n)
    s = rng.uniform(math.sin(math.radians(elev_lo)), math.sin(math.radians(elev_hi)), n)
    c = np.sqrt(1 - s**2)
    return RADIUS * np.stack([c * np.cos(az), c * np.sin(az), s], -1)


def prepare_mesh(obj: dict, src_root: Path, rng: np.random.Generator) -> tuple[Mesh, dict]:
    """The object's mesh in the corpus world (z up, random yaw, radius 0.9-1.3) with appearance
    enrichment for untextured meshes (a triplanar texture, a random base colour)."""
    notes: dict = {}
    if obj["kind"] == "procedural":
        mesh = random_shape(rng)
    elif obj["kind"] == "kitbash":
        mesh = kitbash_shape(rng)
    else:
        mesh = load_mesh(src_root / obj["repo"].replace("/", "+") / obj["path"])
        if obj.get("y_up", True):
            mesh = y_up_to_z_up(mesh)
        if len(mesh.faces) > 400_000:
            raise InputError(f"{len(mesh.faces)} triangles: too many for the corpus renderer")
    yaw = rng.uniform(0, 2 * np.pi)
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    mesh.vertices = mesh.vertices @ Rz.T
    if obj["kind"] == "procedural" and rng.random() < 0.3:
        mesh.vertices = mesh.vertices @ random_rotation(rng).T
    mesh = normalise(mesh, rng.uniform(0.9, 1.3))
    uniform = np.ptp(mesh.face_colors, axis=0).max() < 0.05 and not mesh.textures
    if uniform:
        mesh.face_colors = np.tile(rng.uniform(0.1, 0.95, 3), (len(mesh.faces), 1))
    if not mesh.textures and (uniform or rng.random() < (0.15 if obj["kind"] == "kitbash" else 0.5)):
        mesh.triplanar, notes["texture"] = random_texture(rng)
        mesh.triplanar_scale = float(rng.uniform(0.3, 1.5))
    return mesh, notes


NOVEL_ELEVATIONS = (-10.0, 80.0)  # degrees: the novel views' band (the shape corpus takes the whole sphere)


def render_scene(
    mesh: Mesh,
    out: Path,
    rng: np.random.Generator,
    size: int,
    n_train: int,
    n_test: int,
    novel_elevations: tuple[float, float] = NOVEL_ELEVATIONS,
) -> None:
    """Blender-format scene: train views on the upper hemisphere (5-75 degrees), test (novel) views
    between the two `novel_elevations`."""
    f = 0.5 * size / math.tan(0.5 * FOV_X)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    for split, eyes in (
        ("train", sphere_eyes(rng, n_train, 5, 75)),
        ("test", sphere_eyes(rng, n_test, *novel_elevations)),
    ):
        frames = []
        for i, eye in enumerate(eyes):
            c2w = look_at_c2w(eye)
            rgba = render_rgba(mesh, c2w_to_viewmat(c2w), K, size, size)
            write_png(out / split / f"r_{i}.png", rgba)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (out / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV_X, "frames": frames}))


def build_object(
    obj: dict,
    src_root: Path,
    out: Path,
    size: int,
    n_train: int,
    n_test: int,
    novel_elevations: tuple[float, float] = NOVEL_ELEVATIONS,
) -> dict:
    seed = int(hashlib.sha1(obj["name"].encode()).hexdigest(), 16) % 2**31
    rng = np.random.default_rng(seed)
    mesh, notes = prepare_mesh(obj, src_root, rng)
    render_scene(mesh, out, rng, size, n_train, n_test, novel_elevations)
    record = {
        **obj,
        **notes,
        "faces": int(len(mesh.faces)),
        "size": size,
        "holdout": is_holdout(obj["name"]),
        "novel_elevations": list(novel_elevations),
    }
    (out / "object.json").write_text(json.dumps(record, indent=1))
    return record


def render_objects(
    objs: list[dict],
    src_root: Path,
    cache: Path,
    size: int,
    n_train: int,
    n_test: int,
    novel_elevations: tuple[float, float] = NOVEL_ELEVATIONS,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
) -> int:
    """Render each object's scene unless done (workers > 1: one-thread processes, round-robin)."""
    if workers > 1:
        from .pairs import in_processes

        return sum(
            in_processes(render_objects, workers, objs, src_root, cache, size, n_train, n_test, novel_elevations)
        )
    made = 0
    for i, obj in enumerate(objs):
        out = cache / "objects" / obj["name"]
        if i % shard[1] != shard[0] or (out / "object.json").is_file():
            continue
        try:
            build_object(obj, src_root, out, size, n_train, n_test, novel_elevations)
            made += 1
            log(f"corpus: [{i + 1}/{len(objs)}] {obj['name']}")
        except (InputError, ValueError) as exc:
            log(f"corpus: skipped {obj['name']}: {exc}")
    return made


def build_corpus(
    mirror: Path,
    cache: Path,
    n_procedural: int,
    limit: int | None,
    size: int = 128,
    n_train: int = 24,
    n_test: int = 24,
    first_procedural: int = 0,
    workers: int = 1,
    n_kitbash: int = 0,
    novel_elevations: tuple[float, float] = NOVEL_ELEVATIONS,
) -> list[dict]:
    """Extract the fetched snapshots, list objects, render each (skipping finished ones)."""
    src_root = cache / "src"
    missing_total: dict[str, list[str]] = {}
    snapshots: dict[str, str] = {}
    for repo in sorted({s.repo for s in SOURCES}):
        git_dir = snapshot_dir(mirror, repo)
        if git_dir is None:
            log(f"corpus: {repo} not fetched (skipped); fetch it to include its objects")
            continue
        snapshots[repo] = subprocess.run(
            ["git", "--git-dir", str(git_dir), "rev-parse", "HEAD"], check=True, capture_output=True, text=True
        ).stdout.strip()
        n, missing = extract(git_dir, src_root / repo.replace("/", "+"))
        missing_total[repo] = missing
        log(f"corpus: {repo}: {n} files, {len(missing)} missing from the snapshot (>= 4 MiB)")
    groups: dict[str, list[dict]] = {}
    for o in list_objects(src_root):
        groups.setdefault(o["repo"], []).append(o)
    objs = interleave(
        [
            procedural_objects(n_procedural, first_procedural),
            procedural_objects(n_kitbash, first_procedural, "kitbash"),
            *groups.values(),
        ]
    )
    if limit is not None:
        objs = objs[:limit]
    render_objects(objs, src_root, cache, size, n_train, n_test, novel_elevations, workers)
    done = [json.loads(p.read_text()) for o in objs if (p := cache / "objects" / o["name"] / "object.json").is_file()]
    (cache / "corpus.json").write_text(
        json.dumps({"objects": done, "snapshots": snapshots, "missing": missing_total}, indent=1)
    )
    return done
