"""The Camera type: centre, JSON and COLMAP round trips, a Frame is a Camera plus images."""

import dataclasses
import json

import numpy as np
import torch

from wgs.scene.camera import Camera, camera_center
from wgs.scene.convention import invert_rigid
from wgs.scene.dataset import Frame
from wgs.scene.orbit import look_at


def test_center_is_the_camera_position_for_numpy_and_torch():
    eye = np.array([0.3, -2.0, 1.1])
    w2c = look_at(eye, np.zeros(3), np.array([0, 0, 1.0]))
    np.testing.assert_allclose(camera_center(w2c), eye, atol=1e-12)
    np.testing.assert_allclose(camera_center(w2c), invert_rigid(w2c)[:3, 3], atol=1e-12)
    cam = Camera(torch.eye(3), torch.tensor(w2c, dtype=torch.float32), 8, 6)
    torch.testing.assert_close(cam.center, torch.tensor(eye, dtype=torch.float32))


def test_json_round_trip_and_frames_are_cameras():
    g = torch.Generator().manual_seed(0)
    cam = Camera(torch.rand(3, 3, generator=g), torch.rand(4, 4, generator=g), 40, 30)
    back = Camera.from_json(json.loads(json.dumps(cam.to_json())))
    assert (back.width, back.height) == (40, 30) and back.K.dtype == torch.float32
    torch.testing.assert_close(back.K, cam.K)
    torch.testing.assert_close(back.viewmat, cam.viewmat)
    f = Frame(cam.K, cam.viewmat, 40, 30, name="a.png", image=torch.zeros(30, 40, 3))
    assert isinstance(f, Camera) and f.to_json() == cam.to_json()
    g2 = dataclasses.replace(f, image=torch.ones(30, 40, 3))
    assert g2.name == "a.png" and g2.K is f.K and float(g2.image.mean()) == 1.0


def test_colmap_round_trip_and_pycolmap_projects_as_K_viewmat(tmp_path):
    from wgs.scene.colmap import project_point, read_model, write_model

    eye = np.array([0.7, -2.5, 1.3])
    K = torch.tensor([[120.0, 0, 41.5], [0, 118.0, 29.25], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, torch.from_numpy(look_at(eye, np.zeros(3), np.array([0, 0, 1.0]))), 80, 60)
    write_model(tmp_path, {"a.png": cam})
    back = read_model(tmp_path)["a.png"]
    assert (back.width, back.height) == (80, 60)
    torch.testing.assert_close(back.K, cam.K, atol=1e-9, rtol=0)
    torch.testing.assert_close(back.viewmat, cam.viewmat, atol=1e-9, rtol=0)
    X = np.array([0.2, -0.1, 0.3])
    x = (cam.K @ (cam.viewmat[:3, :3] @ torch.from_numpy(X) + cam.viewmat[:3, 3])).numpy()
    np.testing.assert_allclose(project_point(tmp_path, "a.png", X), x[:2] / x[2], atol=1e-6)
