"""Localising a test camera on a frozen model (`gaussians.localise`): it finds the camera whose
photo it is, and leaves the model alone."""

import math
from dataclasses import replace

import numpy as np
import torch

from wgs.gaussians.localise import axis_angle_quat, camera_delta, localise, move_world
from wgs.gaussians.pose_refine import CameraCorrections
from wgs.gaussians.project import quat_to_rotmat
from wgs.gaussians.render import rasterize
from wgs.gaussians.splats import activate, create_splats
from wgs.gaussians.trainer import render_frame
from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at

SIZE = 48


def angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def textured_blob(n=300, seed=0):
    """Gaussians in a ball, each of its own colour: a model with texture to localise on."""
    g = torch.Generator().manual_seed(seed)
    points = torch.randn(n, 3, generator=g) * 0.35
    return create_splats(points, torch.rand(n, 3, generator=g), torch.full((n,), 0.08), 0, opacity=0.8)


def camera(viewmat: np.ndarray) -> Frame:
    K = torch.tensor([[55.0, 0, SIZE / 2], [0, 55, SIZE / 2], [0, 0, 1]])
    return Frame(K, torch.tensor(viewmat, dtype=torch.float32), SIZE, SIZE, name="t.png")


def photo_at(splats, frame: Frame, bg: torch.Tensor) -> Frame:
    rgb, alpha = render_frame(splats, frame, torch.device("cpu"), bg)
    return Frame(frame.K, frame.viewmat, SIZE, SIZE, name=frame.name, image=rgb, mask=alpha[..., 0])


def turned(viewmat: np.ndarray, degrees: float, shift: float) -> np.ndarray:
    """The camera turned about its own y axis and shifted along its x axis."""
    a = math.radians(degrees)
    delta = np.eye(4)
    delta[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    delta[0, 3] = shift
    return delta @ viewmat


def test_smoke_no_steps_leaves_the_camera():
    splats, bg = textured_blob(), torch.ones(3)
    truth = photo_at(splats, camera(look_at(np.array([0, -2.5, 0.5]), np.zeros(3), np.array([0, 0, 1.0]))), bg)
    moved, delta = localise(splats, truth, bg, steps=0)
    assert torch.equal(moved.viewmat, truth.viewmat) and torch.equal(delta, torch.eye(4))


def test_a_camera_two_degrees_off_is_brought_back_and_the_model_does_not_move():
    splats, bg = textured_blob(), torch.ones(3)
    true_w2c = look_at(np.array([0, -2.5, 0.5]), np.zeros(3), np.array([0, 0, 1.0]))
    photo = photo_at(splats, camera(true_w2c), bg)
    off = replace(photo, viewmat=torch.tensor(turned(true_w2c, 2.0, 0.03), dtype=torch.float32))
    before = {k: v.clone() for k, v in splats.items()}
    moved, _ = localise(splats, off, bg, steps=150, lr=2e-3)
    err_before = angle_deg(off.viewmat[:3, :3].double().numpy() @ true_w2c[:3, :3].T)
    err_after = angle_deg(moved.viewmat[:3, :3].double().numpy() @ true_w2c[:3, :3].T)
    assert err_before > 1.9
    assert err_after < 0.5, err_after
    assert all(torch.equal(splats[k], before[k]) for k in splats)
    assert moved.image is photo.image and moved.K is photo.K  # only the pose changes


def test_axis_angle_quat_is_a_unit_rotation_by_the_angle_and_smooth_at_zero():
    omega = torch.tensor([0.0, 0.3, 0.4])
    q = axis_angle_quat(omega)
    assert torch.allclose(q.norm(), torch.tensor(1.0))
    R = quat_to_rotmat(q[None])[0].double().numpy()
    assert math.isclose(angle_deg(R), math.degrees(0.5), rel_tol=1e-5)
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(axis_angle_quat, (zero,))
    torch.autograd.gradcheck(axis_angle_quat, (omega.double().requires_grad_(),))


def test_the_moved_world_seen_from_a_camera_is_the_world_seen_from_the_corrected_camera():
    g = torch.Generator().manual_seed(3)
    means = torch.randn(20, 3, generator=g, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(20, 4, generator=g, dtype=torch.float64), dim=-1)
    viewmat = torch.tensor(look_at(np.array([0.3, -2.5, 0.5]), np.zeros(3), np.array([0, 0, 1.0])))
    omega, tau = torch.tensor([0.02, -0.03, 0.01], dtype=torch.float64), torch.tensor([0.05, 0.0, -0.02]).double()
    moved, q = move_world(means, quats, viewmat, omega, tau)
    delta = camera_delta(omega, tau)
    corrected = delta @ viewmat
    # the same points in the camera's frame, and the same orientations
    assert torch.allclose(moved @ viewmat[:3, :3].T + viewmat[:3, 3], means @ corrected[:3, :3].T + corrected[:3, 3])
    assert torch.allclose(viewmat[:3, :3] @ quat_to_rotmat(q), corrected[:3, :3] @ quat_to_rotmat(quats))
    same, same_q = move_world(means, quats, viewmat, torch.zeros(3).double(), torch.zeros(3).double())
    assert torch.allclose(same, means) and torch.allclose(same_q, quats)


def test_gradcheck_move_world():
    g = torch.Generator().manual_seed(4)
    means = torch.randn(5, 3, generator=g, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(5, 4, generator=g, dtype=torch.float64), dim=-1)
    viewmat = torch.tensor(look_at(np.array([0.3, -2.5, 0.5]), np.zeros(3), np.array([0, 0, 1.0])))
    omega = torch.tensor([0.02, -0.03, 0.01], dtype=torch.float64, requires_grad=True)
    tau = torch.tensor([0.05, 0.0, -0.02], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda o, t: move_world(means, quats, viewmat, o, t), (omega, tau))


def test_camera_corrections_leave_the_first_view_and_move_the_others():
    splats, bg = textured_blob(), torch.ones(3)
    frames = [
        photo_at(splats, camera(look_at(np.array([x, -2.5, 0.5]), np.zeros(3), np.array([0, 0, 1.0]))), bg)
        for x in (0.0, 0.8)
    ]
    cams = CameraCorrections(2, lr=1e-2, device=torch.device("cpu"))
    params = {k: v.requires_grad_() for k, v in splats.items()}
    for i, f in enumerate(frames):
        means, quats, scales, opac, sh = activate(params)
        off = replace(f, viewmat=torch.tensor(turned(f.viewmat.double().numpy(), 2.0, 0.02), dtype=torch.float32))
        m, q = cams.move(i, means, quats, off.viewmat)
        rgb, _, _ = rasterize(m, q, scales, opac, sh, off.viewmat, off.K, SIZE, SIZE, bg)
        (rgb - f.pixels).abs().mean().backward()
    cams.step()
    moved = cams.viewmats([f.viewmat for f in frames])
    assert torch.equal(moved[0], frames[0].viewmat)  # the world's anchor
    assert not torch.equal(moved[1], frames[1].viewmat)
    state = cams.state_dict()
    again = CameraCorrections(2, lr=1e-2, device=torch.device("cpu"))
    again.load_state_dict(state)
    assert all(torch.equal(a, b) for a, b in zip(again.viewmats([f.viewmat for f in frames]), moved, strict=True))
