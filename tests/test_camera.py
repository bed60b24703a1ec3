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
