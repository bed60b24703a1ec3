"""bind_correction against its oracle: template_model, canvas_observation and the search, one call after the other."""

import pytest
import torch

from torchevtrack import geometry as g
from torchevtrack.camera import Camera
from torchevtrack.mesh import load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.eros import canvas_observation, recency_arrays
from torchevtrack.stages.template import Correction, correct_canvas, newton_search, template_model
from torchevtrack.update import CorrectionStep, bind_correction

CAM = Camera.default()
F64 = torch.float64
T_NOW = 1_000_000
OPTIONS = dict(canvas=64, margin_px=20.0, edge_clip=0.1, silhouette=True, interior=0.7)
SEARCH = dict(dp_px=1.0, dtheta_deg=0.5, iterations=4, max_dz=0.002)
MAX_AGE_US = 40_000
RECENCY_US = torch.tensor([5_000.0, 2_250.0])  # one window per element
Z_SHIFT = torch.tensor([0.001, -0.001], dtype=F64)  # the depth bands' centres from the predicted depths


@pytest.fixture(scope="module")
def scene():
    """Two elements: the box and the mustard bottle, each rendered in a 200 x 200 window around its pose, an EROS
    of their edges a few pixels off, with noise, and a time surface of recent and stale events."""
    gen = torch.Generator().manual_seed(0)
    pose = torch.tensor([[0.03, -0.02, 0.5], [-0.04, 0.02, 0.55]], dtype=F64)
    pose = torch.cat((pose, g.quat_exp(torch.tensor([[0.4, -0.6, 0.3], [-0.2, 0.5, 0.1]], dtype=F64))), -1)
    origin = torch.tensor([[250, 140], [180, 160]])
    depth, gray = torch.empty(2, 200, 200), torch.empty(2, 200, 200)
    for i, name in enumerate(("box", "006_mustard_bottle")):
        with RasterRenderer(load_mesh(name, decimate=4000), CAM) as r:
            out = r.render(pose[i:i + 1].float().double(), roi=(*origin[i].tolist(), 200, 200))
        depth[i], gray[i] = out.depth[0], out.gray[0]
    surface = torch.zeros(2, CAM.height, CAM.width)
    for i in range(2):
        u, v = origin[i].tolist()
        edge = (depth[i] > 0).float()
        edge = (edge - torch.nn.functional.avg_pool2d(edge[None], 3, 1, 1)[0]).abs() > 0.1
        surface[i, v + 3:v + 203, u + 2:u + 202] = edge.float() * 0.8
    surface += (torch.rand(surface.shape, generator=gen) > 0.995).float() * 0.5
    last = T_NOW - torch.randint(0, 60_000, (2, 2, CAM.height, CAM.width), generator=gen)
    moved = g.quat_exp(torch.tensor([[0.01, -0.005, 0.008]], dtype=F64).expand(2, 3))
    predicted = torch.cat((pose[:, :3] + torch.tensor([0.002, -0.001, 0.003], dtype=F64), g.quat_mul(moved, pose[:, 3:])),
                          -1)
    return pose.float(), predicted, depth, gray, origin, surface, last, torch.full((2,), T_NOW)


def _oracle(pose32, predicted, depth, gray, origin, surface, last, t_now, rule="newton"):
    model = template_model(pose32, depth, gray, origin, CAM, **OPTIONS)
    obs = canvas_observation(surface, last, model.box, OPTIONS["canvas"], t_now, MAX_AGE_US, RECENCY_US)
    if rule == "newton":
        return model, newton_search(model, predicted, obs.flatten(1), CAM, **SEARCH, z_ref=predicted[:, 2] + Z_SHIFT)
    return model, correct_canvas(model, predicted, obs, CAM, rule=rule, **SEARCH, z_ref=predicted[:, 2] + Z_SHIFT)


def _step(pose32, predicted, depth, gray, origin, surface, last, t_now, rule="newton", model=None, on_observed=None):
    """The tracker's call: the correction bound to the surfaces, on numpy arrays; the correction's fields as
    tensors."""
    run = bind_correction(surface.numpy(), last.numpy(), CAM, **OPTIONS, **SEARCH, rule=rule, max_age_us=MAX_AGE_US,
                          recency=recency_arrays(RECENCY_US, 2, MAX_AGE_US))
    np_ = lambda x: None if x is None else x.numpy()  # noqa: E731
    step = run(np_(pose32), predicted.numpy(), np_(depth), np_(gray), np_(origin), t_now.numpy(), model=model,
               on_observed=on_observed, z_ref=(predicted[:, 2] + Z_SHIFT).numpy())
    return CorrectionStep(step.model, Correction(*(torch.from_numpy(a) for a in step.correction)))


def _assert_equal(a, b):
    for x, y in zip(a, b):
        assert x.dtype == y.dtype and torch.equal(x, y)


@pytest.mark.parametrize("rule", ["newton", "argmax", "group"])
@pytest.mark.parametrize("shaded", [True, False])
def test_the_bound_correction_is_the_stage_calls_bit_for_bit(scene, rule, shaded):
    pose32, predicted, depth, gray, origin, surface, last, t_now = scene
    gray = gray if shaded else None
    model, corr = _oracle(pose32, predicted, depth, gray, origin, surface, last, t_now, rule)
    step = _step(pose32, predicted, depth, gray, origin, surface, last, t_now, rule=rule)
    _assert_equal(step.model, model)
    _assert_equal(step.correction, corr)
    if rule == "newton":
        assert bool((corr.iterations > 0).all())  # the search moved: the comparison covers the Newton rounds


def test_a_reused_model_skips_the_render_and_gives_the_same_correction(scene):
    pose32, predicted, depth, gray, origin, surface, last, t_now = scene
    first = _step(pose32, predicted, depth, gray, origin, surface, last, t_now)
    again = _step(None, predicted, None, None, None, surface, last, t_now, model=first.model)
    assert again.model is first.model
    _assert_equal(again.correction, first.correction)


def test_the_surfaces_are_not_read_after_on_observed(scene):
    pose32, predicted, depth, gray, origin, surface, last, t_now = scene
    ref = _step(pose32, predicted, depth, gray, origin, surface, last, t_now)
    surface, last = surface.clone(), last.clone()
    calls = []

    def observed():  # the next window's events may land now: here they wipe everything
        calls.append(1)
        surface.zero_()
        last.fill_(0)

    step = _step(pose32, predicted, depth, gray, origin, surface, last, t_now, on_observed=observed)
    assert calls == [1]
    _assert_equal(step.correction, ref.correction)
    wiped = _step(pose32, predicted, depth, gray, origin, surface, last, t_now)
    assert not torch.equal(wiped.correction.pose, ref.correction.pose)  # the test would see a late read
