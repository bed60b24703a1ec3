import json

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera


def test_project_backproject_roundtrip():
    cam = Camera.default()
    pts = torch.rand(100, 3, dtype=torch.float64) * torch.tensor([0.4, 0.3, 0.5], dtype=torch.float64) + torch.tensor([-0.2, -0.15, 0.3], dtype=torch.float64)
    uv = cam.project(pts)
    K = cam.K().numpy()
    hom = pts.numpy() @ K.T
    np.testing.assert_allclose(uv.numpy(), hom[:, :2] / hom[:, 2:], atol=1e-10)
    np.testing.assert_allclose(cam.backproject(uv, pts[:, 2]).numpy(), pts.numpy(), atol=1e-12)


def test_crop_keeps_pixels_consistent():
    cam = Camera.default()
    p = torch.tensor([[0.05, -0.02, 0.4]])
    crop = cam.crop(100, 50, 200, 150)
    np.testing.assert_allclose((crop.project(p) + torch.tensor([100.0, 50.0])).numpy(), cam.project(p).numpy(), atol=1e-5)


def test_pixel_grid_layout():
    grid = Camera(4, 3, 1, 1, 0, 0).pixel_grid()
    assert grid.shape == (3, 4, 2)
    assert grid[2, 1].tolist() == [1.0, 2.0]


def test_interaction_matrix_matches_finite_difference():
    cam = Camera.default()
    P = torch.tensor([0.05, -0.03, 0.45], dtype=torch.float64)
    twist = torch.tensor([0.1, -0.2, 0.3, 0.5, -0.4, 0.7], dtype=torch.float64)
    dt = 1e-7
    P2 = P + (twist[:3] + torch.linalg.cross(twist[3:], P)) * dt
    numeric = (cam.project(P2) - cam.project(P)) / dt
    L = cam.interaction_matrix(cam.project(P), P[2])
    np.testing.assert_allclose((L @ twist).numpy(), numeric.numpy(), rtol=1e-5)


def test_save_load_and_errors(tmp_path):
    cam = Camera(64, 48, 50.0, 51.0, 31.5, 23.5)
    cam.save(tmp_path / "camera.json")
    assert Camera.load(tmp_path / "camera.json") == cam
    with pytest.raises(FileNotFoundError):
        Camera.load(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text(json.dumps({"width": 10}))
    with pytest.raises(ValueError, match="lacks"):
        Camera.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="positive"):
        Camera(0, 10, 1, 1, 0, 0)


@pytest.mark.parametrize("key, value, message", [
    ("fx", "500", "camera fx must be a number"),
    ("cx", float("nan"), "camera cx must be finite"),
    ("fx", float("inf"), "camera fx must be finite and positive"),
    ("fy", -3.0, "camera fy must be finite and positive"),
    ("width", 100000, "camera width must be a positive whole number"),
    ("width", "640", "camera width must be a positive whole number"),
    ("width", 64.5, "camera width must be a positive whole number"),
    ("height", None, "camera height must be a positive whole number"),
])
def test_bad_intrinsics_are_one_line_errors(tmp_path, key, value, message):
    d = {"width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, key: value}
    (tmp_path / "camera.json").write_text(json.dumps(d))  # NaN / Infinity as JSON allows them in Python
    with pytest.raises(ValueError, match=message) as e:
        Camera.load(tmp_path / "camera.json")
    assert "\n" not in str(e.value)


def test_a_huge_camera_is_refused_at_construction():
    """Every image of the tracker has the camera's size: a 30000 x 30000 sensor would be 3.6 GB per image."""
    with pytest.raises(ValueError, match="30000x30000 is over 16 Mpx"):
        Camera(30000, 30000, 500.0, 500.0, 1.0, 1.0)
    assert Camera(1280, 720, 500.0, 500.0, 640.0, 360.0).width == 1280
