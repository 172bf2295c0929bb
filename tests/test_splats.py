"""Splats: checkpoints (world coordinates, weights_only), PLY layout and round trip."""

import pickle
import struct

import numpy as np
import pytest
import torch

from wgs.errors import InputError
from wgs.gaussians.splats import (
    create_splats,
    export_ply,
    import_ply,
    load_checkpoint,
    ply_attributes,
    save_checkpoint,
    to_world,
)
from wgs.scene.convention import Normalisation


def random_splats(n=50, deg=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    sp = create_splats(
        torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), torch.rand(n, generator=g) * 0.1 + 0.01, deg
    )
    sp["quats"] = torch.randn(n, 4, generator=g)
    sp["shN"] = torch.randn_like(sp["shN"])
    sp["opacities"] = torch.randn(n, generator=g)
    return sp


NORM = Normalisation(np.array([1.0, -2.0, 3.0]), 4.0)


def test_checkpoint_round_trip_in_world_coordinates(tmp_path):
    sp = random_splats()
    save_checkpoint(tmp_path / "c.pt", sp, NORM, step=7)
    raw = torch.load(tmp_path / "c.pt", weights_only=True)
    assert raw["step"] == 7 and set(raw["splats"]) == {"means", "quats", "scales", "opacities", "sh0", "shN"}
    torch.testing.assert_close(raw["splats"]["means"], sp["means"] * 4.0 + torch.tensor([1.0, -2.0, 3.0]))
    back, _ = load_checkpoint(tmp_path / "c.pt", NORM)
    for k in sp:
        torch.testing.assert_close(back[k], sp[k], rtol=1e-6, atol=1e-6)


def test_checkpoint_with_pickle_payload_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    p = tmp_path / "evil.pt"
    with open(p, "wb") as fh:
        pickle.dump({"splats": Evil()}, fh)
    with pytest.raises(InputError, match="not a valid wgs checkpoint"):
        load_checkpoint(p)


@pytest.mark.parametrize("damage", ["truncate", "wrong_shape", "missing_key", "version", "sh_count"])
def test_bad_checkpoints(tmp_path, damage):
    sp = random_splats()
    p = tmp_path / "c.pt"
    save_checkpoint(p, sp, NORM, 1)
    blob = torch.load(p, weights_only=True)
    if damage == "truncate":
        p.write_bytes(p.read_bytes()[:100])
    else:
        if damage == "wrong_shape":
            blob["splats"]["quats"] = blob["splats"]["quats"][:, :3]
        elif damage == "missing_key":
            del blob["splats"]["sh0"]
        elif damage == "version":
            blob["version"] = 99
        else:
            blob["splats"]["shN"] = torch.zeros(50, 5, 3)
        torch.save(blob, p)
    with pytest.raises(InputError) as exc:
        load_checkpoint(p)
    assert str(p) in str(exc.value)


def test_ply_layout_is_3dgs(tmp_path):
    sp = random_splats(n=5, deg=1)
    p = tmp_path / "a.ply"
    assert export_ply(p, sp) == 5
    raw = p.read_bytes()
    header, body = raw.split(b"end_header\n")
    lines = header.decode().splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    props = [ln.split()[2] for ln in lines if ln.startswith("property float")]
    assert props == ply_attributes(1)
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(body) == 5 * len(props) * 4
    row0 = struct.unpack(f"<{len(props)}f", body[: 4 * len(props)])
    # f_rest is channel-major: f_rest_0..2 are the red channel of the 3 degree-1 coefficients
    np.testing.assert_allclose(row0[9:12], sp["shN"][0, :, 0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(row0[12:15], sp["shN"][0, :, 1].numpy(), rtol=1e-6)
    np.testing.assert_allclose(row0[-4:], sp["quats"][0].numpy(), rtol=1e-6)


def test_ply_round_trip_exact(tmp_path):
    sp = random_splats(deg=3)
    export_ply(tmp_path / "a.ply", sp)
    back = import_ply(tmp_path / "a.ply")
    for k in sp:
        assert torch.equal(back[k], sp[k].float()), k


def test_ply_drops_non_finite_rows_and_pads(tmp_path):
    sp = random_splats(n=6, deg=0)
    sp["means"][2, 1] = float("nan")
    sp["scales"][4, 0] = float("inf")
    assert export_ply(tmp_path / "a.ply", sp, pad_to_degree=3) == 4
    back = import_ply(tmp_path / "a.ply")
    assert back["shN"].shape == (4, 15, 3) and (back["shN"] == 0).all()


def test_to_world_preserves_rotation_and_scales_size():
    sp = random_splats()
    w = to_world(sp, NORM)
    torch.testing.assert_close(w["quats"], sp["quats"])
    torch.testing.assert_close(torch.exp(w["scales"]), torch.exp(sp["scales"]) * 4.0)


def test_bad_ply(tmp_path):
    p = tmp_path / "x.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(InputError, match="binary"):
        import_ply(p)
