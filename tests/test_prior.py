"""The repair prior: corpus loaders (Draco glTF, glTF/GLB, OBJ), the mesh renderer, procedural
objects, the corpus -> pairs -> training chain on a tiny scale, and the shipped weights."""

from __future__ import annotations

import base64
import json
import math
import struct

import numpy as np
import pytest
import torch

from tools.prior.meshes import Mesh, load_gltf, load_mesh, normalise
from tools.prior.raster import rasterize, render_rgba
from wgs.errors import InputError

QUAD_V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
QUAD_F = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def _gltf(
    tmp_path,
    prim: dict,
    buffers: list[bytes],
    views: list[dict],
    accessors: list[dict],
    node: dict,
    materials=None,
    name="m.gltf",
):
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{**node, "mesh": 0}],
        "meshes": [{"primitives": [prim]}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [
            {"byteLength": len(b), "uri": "data:application/octet-stream;base64," + base64.b64encode(b).decode()}
            for b in buffers
        ],
        "materials": materials or [{"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.4, 0.6, 1]}}],
    }
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path, doc


def test_gltf_plain_accessors_and_node_transform(tmp_path):
    data = QUAD_V.tobytes() + QUAD_F.astype(np.uint16).tobytes()
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 12}]
    acc = [
        {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    path, doc = _gltf(
        tmp_path,
        {"attributes": {"POSITION": 0}, "indices": 1, "material": 0},
        [data],
        views,
        acc,
        {"translation": [0, 0, 2], "scale": [2, 2, 2]},
    )
    m = load_gltf(path)
    np.testing.assert_allclose(m.vertices, QUAD_V * 2 + [0, 0, 2])
    np.testing.assert_array_equal(m.faces, QUAD_F)
    np.testing.assert_allclose(m.face_colors, [[0.2, 0.4, 0.6]] * 2)
    # the same scene as a GLB (JSON chunk + BIN chunk)
    doc["buffers"] = [{"byteLength": len(data)}]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    pad = data + b"\0" * (-len(data) % 4)
    glb = (
        b"glTF"
        + struct.pack("<II", 2, 28 + len(js) + len(pad))
        + struct.pack("<I", len(js))
        + b"JSON"
        + js
        + struct.pack("<I", len(pad))
        + b"BIN\0"
        + pad
    )
    (tmp_path / "m.glb").write_bytes(glb)
    np.testing.assert_allclose(load_mesh(tmp_path / "m.glb").vertices, m.vertices)


def test_gltf_draco(tmp_path):
    DracoPy = pytest.importorskip("DracoPy")
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    blob = DracoPy.encode(QUAD_V, QUAD_F, preserve_order=True, tex_coord=uv)
    prim = {
        "attributes": {"POSITION": 0, "TEXCOORD_0": 1},
        "indices": 2,
        "material": 0,
        "extensions": {"KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0, "TEXCOORD_0": 1}}},
    }
    acc = [
        {"componentType": 5126, "count": 4, "type": "VEC3"},
        {"componentType": 5126, "count": 4, "type": "VEC2"},
        {"componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    path, _ = _gltf(tmp_path, prim, [blob], [{"buffer": 0, "byteLength": len(blob)}], acc, {})
    m = load_gltf(path)
    assert m.faces.shape == (2, 3)
    assert abs(np.abs(m.vertices).max() - 1) < 1e-3  # quantised positions
    assert m.uv is None  # no baseColorTexture: texture coordinates are dropped
    # the two triangles cover the unit quad: area 4
    v = m.vertices[m.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    assert abs(area - 4) < 1e-2


def test_obj_with_texture(tmp_path):
    pytest.importorskip("trimesh")
    from PIL import Image

    Image.fromarray(np.full((4, 4, 3), (255, 0, 0), np.uint8)).save(tmp_path / "tex.png")
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 1 1\nmap_Kd tex.png\n")
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl red\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    )
    m = load_mesh(tmp_path / "m.obj")
    assert m.faces.shape == (2, 3) and len(m.textures) == 1
    np.testing.assert_allclose(m.textures[0][0, 0], [1, 0, 0])


def test_bad_mesh_files(tmp_path):
    (tmp_path / "lfs.obj").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 9\n")
    with pytest.raises(InputError, match="Git LFS pointer"):
        load_mesh(tmp_path / "lfs.obj")
    (tmp_path / "bad.gltf").write_text("{not json")
    with pytest.raises(InputError, match="bad.gltf"):
        load_mesh(tmp_path / "bad.gltf")
    (tmp_path / "x.ply").write_text("ply")
    with pytest.raises(InputError, match="unknown mesh format"):
        load_mesh(tmp_path / "x.ply")


def _camera(size=32, dist=4.0):
    f = size / 2 / math.tan(0.35)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    viewmat = np.eye(4)
    viewmat[2, 3] = dist  # looking down +z at the origin from z = -dist
    return K, viewmat


def test_renderer_coverage_and_depth_order():
    K, viewmat = _camera()
    quad = Mesh(QUAD_V * 0.5, QUAD_F, np.array([[1.0, 0, 0]] * 2))
    rgba = render_rgba(quad, viewmat, K, 32, 32, supersample=4)
    # a 1x1 square at depth 4: its image side is f / 4 pixels
    side = K[0, 0] / 4
    assert abs(rgba[..., 3].sum() - side**2) / side**2 < 0.03
    inside = rgba[16, 16]
    assert inside[3] == 1 and inside[1] == 0 and inside[2] == 0 and inside[0] > 0.3
    # a green quad in front hides the red one; behind, it does not
    for z, visible in ((-0.5, "green"), (0.5, "red")):
        green = Mesh(QUAD_V * 0.3 + [0, 0, z], QUAD_F, np.array([[0, 1.0, 0]] * 2))
        from tools.prior.meshes import concat

        px = render_rgba(concat([quad, green]), viewmat, K, 32, 32)[16, 16]
        assert (px[1] > px[0]) == (visible == "green")
    tri, bary, depth = rasterize(quad.vertices, quad.faces, viewmat, K, 32, 32)
    hit = tri >= 0
    np.testing.assert_allclose(bary[hit].sum(-1), 1, atol=1e-9)
    np.testing.assert_allclose(depth[hit], 4.0, atol=1e-9)


def test_procedural_objects_render():
    from tools.prior.procedural import random_shape, random_texture

    rng = np.random.default_rng(0)
    mesh = normalise(random_shape(rng), 1.0)
    assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0)
    mesh.triplanar, _ = random_texture(rng, 32)
    K, viewmat = _camera(24)
    rgba = render_rgba(mesh, viewmat, K, 24, 24)
    assert rgba.shape == (24, 24, 4) and 0 < rgba[..., 3].mean() < 1 and np.isfinite(rgba).all()


def test_corpus_pairs_train_chain(tmp_path):
    """One procedural object -> Blender scene -> our coarse stage -> pairs -> a few prior steps; the
    result loads as a prior and the fine-tune keeps it when no step beats it."""
    from tools.prior.corpus import build_object, procedural_objects
    from tools.prior.pairs import object_pairs
    from tools.prior.train import PriorConfig, pack_pairs, train_prior
    from wgs.models.storage import load_model
    from wgs.scene.formats import read_scene
    from wgs.workspace import Workspace

    obj = procedural_objects(1)[0]
    scene = tmp_path / "obj"
    build_object(obj, tmp_path, scene, 32, 8, 4)
    assert read_scene(scene).format == "blender"
    arrays = object_pairs(scene, tmp_path / "ws", 4, {"iterations": 20, "init_points": 500, "hull_resolution": 24})
    assert arrays["render"].shape == (4, 32, 32, 3) and arrays["ref"].dtype == np.uint8
    assert Workspace(tmp_path / "ws").manifest("coarse")["ensemble"] == 1  # G_c alone, not the product's ensemble
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    for name, hold in (("a", False), ("b", True)):
        np.savez_compressed(pairs / f"{name}.npz", **arrays, holdout=np.bool_(hold))
    pack_pairs(pairs, tmp_path / "pack.npz")
    cfg = PriorConfig(
        d_channels=8, d_steps=4, d_batch=2, d_crop=8, u_channels=8, u_steps=4, u_batch=2, u_crop=16, eval_every=2
    )
    rec = train_prior(tmp_path / "pack.npz", tmp_path / "prior", cfg, torch.device("cpu"), log=lambda m: None)
    assert rec["pairs"] == 8 and rec["holdout_pairs"] == 4
    D, d_cfg = load_model(tmp_path / "prior" / "D")
    assert d_cfg["start"] == "corrupted" and d_cfg["t_max"] == cfg.t_max
    # the same pairs carry the hull channels S trains on; the hull holds the object's alpha
    assert arrays["hull"].shape == (4, 32, 32) and arrays["hull_depth"].dtype == np.float16
    obj_px = arrays["ref_alpha"] > 127
    assert (arrays["hull"][obj_px] > 127).mean() > 0.95
    from tools.prior.train_shape import ShapeTrainConfig, load_shape_pairs, train_silhouette
    from wgs.models.silhouette_net import SilhouetteNet, SilhouetteNetConfig

    net = SilhouetteNetConfig(channels=8, levels=2, work_size=48)
    data = load_shape_pairs(pairs, net.work_size)
    assert data["inputs"].shape == (8, 6, 48, 48) and int(data["holdout"].sum()) == 4  # at S's working size
    S, curve = train_silhouette(
        data, ShapeTrainConfig(net=net, steps=3, batch=2, eval_every=2), torch.device("cpu"), log=lambda m: None
    )
    assert isinstance(S, SilhouetteNet) and S.config.levels == 2 and curve["step"] == [2, 3]
    assert 0 <= curve["val"][-1]["S_iou"] <= 1 and curve["val"][-1]["hull_missed"] < 0.05


def test_volume_pairs_train_chain(tmp_path):
    """One procedural object -> Blender scene -> (few-view hull, many-view hull) cubes -> a few V steps."""
    from tools.prior.corpus import build_object, procedural_objects
    from tools.prior.train_volume import VolumeTrainConfig, load_volume_pairs, train_volume
    from tools.prior.volume_pairs import object_volume_pairs
    from wgs.models.volume_net import VolumeNet, VolumeNetConfig

    obj = procedural_objects(1)[0]
    scene = tmp_path / "obj"
    build_object(obj, tmp_path, scene, 32, 8, 4)
    arrays = object_volume_pairs(scene, tmp_path / "ws", subsets=3, resolution=16)
    assert arrays["x"].shape == (3, 4, 16, 16, 16) and arrays["y"].shape == (3, 16, 16, 16)
    hull, target = arrays["x"][:, 0] > 0.5, arrays["y"] > 0
    assert target.any() and not (target & ~hull).any()  # more views, less hull
    pairs = tmp_path / "volume_pairs"
    pairs.mkdir()
    for name, hold in (("a", False), ("b", True), ("cow-like", False)):
        np.savez_compressed(pairs / f"{name}.npz", **arrays, holdout=np.bool_(hold))
    data = load_volume_pairs(pairs, exclude=("cow*",))
    assert data["names"] == ["a", "b"] and int(data["holdout"].sum()) == 3
    cfg = VolumeTrainConfig(net=VolumeNetConfig(channels=8, levels=1, resolution=16), steps=3, batch=2, eval_every=2)
    V, curve = train_volume(data, cfg, torch.device("cpu"), log=lambda m: None)
    assert isinstance(V, VolumeNet) and curve["step"] == [2, 3]
    held = curve["val"][-1]
    assert all(0 <= held[k] <= 1 for k in ("V_iou", "hull_iou", "excess_cut", "object_lost"))


def test_prior_finetune_keeps_the_prior_unless_beaten():
    from wgs.models.storage import load_model
    from wgs.stages.finetune.settings import FinetuneConfig
    from wgs.training.per_object import finetune_prior_d
    from wgs.weights import WEIGHTS

    g = torch.Generator().manual_seed(0)
    clean = torch.rand(6, 3, 16, 16, generator=g) * 2 - 1
    bad = clean + 0.3 * torch.randn(6, 3, 16, 16, generator=g)
    cfg = FinetuneConfig(prior_steps=4, prior_eval_every=2, prior_lr=0.5, d_batch=2, d_crop=8)  # a harmful lr
    model, meta, curve = finetune_prior_d(cfg, WEIGHTS, clean[:4], bad[:4], clean[4:], bad[4:], torch.device("cpu"), g)
    assert meta.start == "corrupted" and meta.prior == str(WEIGHTS)
    assert curve["best"] <= curve["bar"]
    if curve["best"] == curve["bar"]:  # nothing beat the prior: its weights are back
        prior, _ = load_model(WEIGHTS / "D")
        for a, b in zip(model.state_dict().values(), prior.state_dict().values(), strict=True):
            torch.testing.assert_close(a, b)


def test_single_step_is_deterministic_at_t0():
    from wgs.models.sampling import single_step
    from wgs.models.scheduler import DDIMScheduler
    from wgs.models.storage import load_model
    from wgs.weights import WEIGHTS

    D, d_cfg = load_model(WEIGHTS / "D")
    x = torch.rand(1, 3, 20, 24) * 2 - 1
    a = single_step(D, DDIMScheduler(), x, 0)
    b = single_step(D, DDIMScheduler(), x, 0)
    assert a.shape == x.shape and torch.equal(a, b)


def test_shipped_prior_loads_with_provenance():
    from wgs.models.storage import load_model
    from wgs.weights import WEIGHTS

    for name in ("D", "U"):
        model, cfg = load_model(WEIGHTS / name)
        assert sum(p.numel() for p in model.parameters()) > 1000
    prov = json.loads((WEIGHTS / "provenance.json").read_text())
    assert prov["pairs"] > 0 and prov["sources"]
    assert all(s["licence"] for s in prov["sources"])
    assert not any("lego" in s["name"] or "nerf" in s["name"].lower() for s in prov["sources"])


def test_shipped_silhouette_model_loads_with_provenance():
    from wgs.models.silhouette_net import SilhouetteNet
    from wgs.models.storage import load_model
    from wgs.weights import WEIGHTS_S

    model, _ = load_model(WEIGHTS_S)
    assert isinstance(model, SilhouetteNet)
    prov = json.loads((WEIGHTS_S / "provenance.json").read_text())
    held = prov["curve"]["val"][-1]
    assert prov["holdout_objects"] and held["S_iou"] > held["hull_iou"]  # S beats the hull on unseen objects
    assert not any("lego" in n or "nerf" in n.lower() for n in prov["objects"])


def test_shipped_volume_model_loads_with_provenance():
    from wgs.models.storage import load_model
    from wgs.models.volume_net import VolumeNet
    from wgs.weights import WEIGHTS_V

    model, _ = load_model(WEIGHTS_V)
    assert isinstance(model, VolumeNet)
    prov = json.loads((WEIGHTS_V / "provenance.json").read_text())
    held = prov["curve"]["val"][-1]
    assert held["V_iou"] > held["hull_iou"]  # V beats the strict hull on objects it never saw
    # generated objects only: the corpus's fetched meshes carry licences that do not all allow shipping weights
    assert all(n.startswith(("procedural-", "kitbash-")) for n in prov["objects"])


def test_kitbash_shape_is_many_flat_coloured_parts():
    from tools.prior.procedural import box, cylinder, kitbash_shape

    assert len(box(np.ones(3)).faces) == 12 and len(cylinder(0.1, 0.2, 8).faces) == 32
    mesh = kitbash_shape(np.random.default_rng(3))
    assert len(mesh.faces) >= 12 * 13 and len(np.unique(mesh.face_colors, axis=0)) >= 2
    viewmat = np.eye(4)
    viewmat[2, 3] = 4.0
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    rgba = render_rgba(mesh, viewmat, K, 32, 32)
    assert 0.05 < rgba[..., 3].mean() < 1


def _tiny_pack(path, n=8, size=16):
    g = np.random.default_rng(0)
    ref = g.integers(0, 256, (n, size, size, 3), dtype=np.uint8)
    render = np.clip(ref.astype(int) + g.integers(-40, 40, ref.shape), 0, 255).astype(np.uint8)
    np.savez_compressed(path, render=render, ref=ref, holdout=np.arange(n) >= n - 2, object=np.arange(n) // 2)
    return path


def test_prior_training_continues_from_its_state_and_starts_from_a_prior(tmp_path):
    from tools.prior.train import PriorConfig, load_pack, train_d, train_prior
    from wgs.models.storage import load_model

    data = load_pack(_tiny_pack(tmp_path / "pack.npz"))
    args = (data["render"], data["ref"], data["holdout"], torch.device("cpu"))
    small = dict(d_channels=8, d_batch=2, d_crop=4, eval_every=2, warmup=1)
    torch.manual_seed(0)  # the model's initial weights
    straight, _, meta = train_d(PriorConfig(d_steps=4, **small), *args, log=lambda m: None)
    assert meta.start == "corrupted" and meta.t_max == PriorConfig.t_max
    state = tmp_path / "state.pt"
    # an interrupted run: the same config, stopped after its first saved state (step 2)
    cfg = PriorConfig(d_steps=4, **small)
    saves = []
    torch.manual_seed(0)
    with pytest.raises(KeyboardInterrupt):
        train_d(cfg, *args, log=lambda m: saves.append(m) or (len(saves) == 1 and _interrupt()), state_path=state)
    assert state.is_file() and torch.load(state, weights_only=True)["loop"]["step"] == 2
    resumed, curve, _ = train_d(cfg, *args, log=lambda m: None, state_path=state)
    assert curve["step"] == [2, 4]
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(InputError, match="another configuration"):
        train_d(PriorConfig(d_steps=6, **small), *args, log=lambda m: None, state_path=state)

    first = tmp_path / "first"
    train_prior(
        tmp_path / "pack.npz",
        first,
        PriorConfig(d_steps=2, u_steps=2, u_channels=8, u_crop=8, **small),
        torch.device("cpu"),
        log=lambda m: None,
    )
    frozen = PriorConfig(d_steps=2, d_lr=0.0, u_steps=0, u_channels=8, **small)  # no step moves the weights
    rec = train_prior(
        tmp_path / "pack.npz", tmp_path / "second", frozen, torch.device("cpu"), log=lambda m: None, init=first
    )
    assert rec["init"]["path"] == str(first) and rec["init"]["provenance"]["pairs"] == 8
    for name in ("D", "U"):
        a, b = load_model(first / name)[0], load_model(tmp_path / "second" / name)[0]
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
            torch.testing.assert_close(x, y)


def _interrupt():
    raise KeyboardInterrupt
