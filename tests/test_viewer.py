"""The browser viewer's pieces: the .splat layout, quaternion helpers (float64 against the
rotation matrices), the upright frame the viewer puts the model in."""

import numpy as np
import pytest
import torch
from conftest import ring_w2c

from wgs.gaussians.project import matrix_to_quat, quat_multiply, quat_to_rotmat
from wgs.gaussians.splats import SPLAT_ROW, splat_bytes
from wgs.viewer import viewer_frame

SPLAT = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def random_rotations(n, seed=0):
    q = torch.nn.functional.normalize(
        torch.randn(n, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64), dim=-1
    )
    return quat_to_rotmat(q)


def test_matrix_to_quat_inverts_quat_to_rotmat_at_every_angle():
    Rs = list(random_rotations(50))
    Rs += [torch.diag(torch.tensor(d, dtype=torch.float64)) for d in ([1, -1, -1], [-1, 1, -1], [-1, -1, 1])]
    Rs.append(torch.eye(3, dtype=torch.float64))  # 180-degree turns and no turn: the hard cases
    for R in Rs:
        q = matrix_to_quat(R)
        assert q.dtype == torch.float64 and abs(float(q.norm()) - 1) < 1e-12
        assert torch.allclose(quat_to_rotmat(q[None])[0], R, atol=1e-12)


def test_quat_multiply_composes_rotations():
    a, b = random_rotations(2, seed=1)
    qa, qb = matrix_to_quat(a), matrix_to_quat(b)
    assert torch.allclose(quat_to_rotmat(quat_multiply(qa, qb)[None])[0], a @ b, atol=1e-12)


def tiny_splats():
    return {
        "means": torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]]),
        "scales": torch.log(torch.tensor([[0.1, 0.1, 0.1], [0.5, 0.2, 0.1]])),
        "opacities": torch.tensor([0.0, 10.0]),
        "sh0": torch.zeros(2, 1, 3),
        "shN": torch.zeros(2, 3, 3),
    }


def test_splat_layout():
    rows = np.frombuffer(splat_bytes(tiny_splats()), SPLAT)
    assert SPLAT.itemsize == SPLAT_ROW and len(rows) == 2
    big = rows[0]  # the larger, more opaque Gaussian comes first
    assert np.allclose(big["pos"], [1, 2, 3]) and np.allclose(big["scale"], [0.5, 0.2, 0.1])
    assert list(big["rgba"][:3]) == [128, 128, 128] and big["rgba"][3] == 255  # SH 0 = grey; sigmoid(10)
    assert list(big["rot"]) == [128, 128, 128, 255]  # (w, x, y, z) = (0, 0, 0, 1), normalised
    assert rows[1]["rgba"][3] == 128 and list(rows[1]["rot"]) == [255, 128, 128, 128]


def test_splat_transform_moves_and_turns_each_gaussian():
    R = random_rotations(1, seed=3)[0].float()
    t = torch.tensor([0.5, -1.0, 2.0])
    sp = tiny_splats()
    rows = np.frombuffer(splat_bytes(sp, R, t), SPLAT)
    assert np.allclose(rows[0]["pos"], (R @ sp["means"][1] + t).numpy(), atol=1e-5)
    q = torch.tensor(rows[0]["rot"], dtype=torch.float64) / 128 - 1  # 8-bit: about 1% per component
    turned = quat_to_rotmat(q[None])[0]
    assert torch.allclose(turned, R.double() @ quat_to_rotmat(torch.tensor([[0.0, 0, 0, 1]]))[0].double(), atol=0.03)


def test_splat_drops_non_finite_rows():
    sp = tiny_splats()
    sp["means"][0, 0] = float("nan")
    assert len(splat_bytes(sp)) == SPLAT_ROW


@pytest.mark.parametrize("height", [0.0, 0.6])
def test_viewer_frame_stands_the_object_up(height):
    w2cs = ring_w2c(6, radius=3.0, height=height)  # z-up world, cameras around the origin
    f = viewer_frame(w2cs)
    assert np.allclose(f.R @ [0, 0, 1], [0, -1, 0], atol=1e-6)  # up -> the viewer's up (y down)
    assert np.allclose(f.t, 0, atol=1e-4)  # the object centre -> the origin (look_at_center's ridge)
    cam = f.R @ (-w2cs[0][:3, :3].T @ w2cs[0][:3, 3]) + f.t
    assert abs(cam[0]) < 1e-6 and cam[2] < 0  # the first camera: straight ahead of the orbit's start
    assert f.radius == pytest.approx(np.linalg.norm(cam)) and f.beta == pytest.approx(np.arcsin(-cam[1] / f.radius))
    assert np.allclose(f.R @ f.R.T, np.eye(3)) and np.linalg.det(f.R) == pytest.approx(1.0)
