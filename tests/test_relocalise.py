"""The re-localiser's search machinery on an observation that is exactly the object's rendered edges."""

from __future__ import annotations

import math

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_conj, quat_log, quat_mul
from torchevtrack.mesh import load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.relocalise import Level, Relocaliser
from torchevtrack.stages.template import apply_steps

CAM = Camera(200, 150, 180.0, 180.0, 100.0, 75.0)
TRUTH = torch.tensor([[0.01, -0.005, 0.35, 0.9, 0.3, 0.2, 0.25]], dtype=torch.float64)
TRUTH[:, 3:] /= TRUTH[:, 3:].norm()


def edge_observation(renderer):
    """EROS-like surface ``(1, H, W)`` = the silhouette and shading edges of the render at TRUTH, all fresh."""
    r = renderer.render(TRUTH)
    m = (r.depth[0] > 0).float()
    g = r.gray[0]
    d = lambda a: (a - torch.roll(a, 1, 0)).abs() + (a - torch.roll(a, 1, 1)).abs()
    s = torch.maximum(d(m).clamp(max=1), (d(g) > 0.05).float() * m)[None]
    last = torch.where(s > 0, 1000, -(2 ** 62)).long()[:, None]
    return s, last


def errors(pose):
    te = float((pose[0, :3] - TRUTH[0, :3]).norm())
    re = math.degrees(float(quat_log(quat_mul(pose[0, 3:], quat_conj(TRUTH[0, 3:]))).norm()))
    return te, re


@pytest.mark.parametrize("step", [
    [0.03, -0.02, 0.0, math.radians(30), 0.0, 0.0],
    pytest.param([-0.02, 0.03, 0.0, 0.0, math.radians(-30), 0.0], marks=pytest.mark.xfail(
        strict=True, reason="known limitation: a 30 deg yaw start ends 0.8 cm / 38 deg off (module docstring)")),
])
def test_finds_pose_one_grid_step_off(step):
    """One grid step (30 deg) about one axis and 3.6 cm in the image plane."""
    renderer = RasterRenderer(load_mesh("box"), CAM)
    radius = float(torch.as_tensor(load_mesh("box").vertices).norm(dim=1).max())
    surface, last = edge_observation(renderer)
    levels = (Level(30.0, (0.0,), 0.06, 64, 0.0), Level(7.5, (0.0,), 0.01, 128, 0.0))
    reloc = Relocaliser(renderer, radius, levels=levels, polish_rounds=1)
    start = apply_steps(TRUTH, torch.tensor([[step]], dtype=torch.float64))[0]
    assert errors(start)[0] > 0.03 and errors(start)[1] > 25
    out = reloc(start, surface, last, torch.tensor([1000]))
    te, re = errors(out.pose)
    assert te < 0.01 and re < 5, (te, re)
    assert bool(out.clear[0]) and float(out.score[0]) > float(out.runner_up[0])


def test_bad_shapes():
    renderer = RasterRenderer(load_mesh("box"), CAM)
    reloc = Relocaliser(renderer, 0.1)
    with pytest.raises(ValueError, match="expected pose"):
        reloc(TRUTH, torch.zeros(150, 200), torch.zeros(1, 1, 150, 200, dtype=torch.int64), torch.tensor([0]))
