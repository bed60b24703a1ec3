"""RenderModelBinding against its oracle: the render window, the rasteriser's render in it and template_model of it,
one call after the other, bit for bit."""

import math

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.mesh import load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.template import camera_array, render_box, render_window, template_model
from torchevtrack.update import RenderModelBinding

CAM = Camera(160, 120, 150.0, 150.0, 79.5, 59.5)
OPTIONS = dict(canvas=64, box_margin_px=12.0, edge_clip=0.2, silhouette=True, interior=0.7)


def render_model(renderer, pose, radius, margin_px=24, shaded=True, model=True, **changes):
    """The tracker's call: the binding of a renderer and the options (``changes`` replace some), on a float64 (1, 7)
    pose."""
    return RenderModelBinding(renderer, radius, margin_px=margin_px, **{**OPTIONS, **changes})(pose.numpy(), shaded,
                                                                                               model)


@pytest.fixture(scope="module")
def renderer():
    r = RasterRenderer(load_mesh("can"), CAM, background=0.25)
    yield r
    r.close()


def _radius(renderer):
    return float(np.linalg.norm(renderer.raster_mesh.vertices, axis=1).max())


def _pose(tx, ty, tz, angle, axis=(0.3, 1.0, 0.2), scale=1.0):
    """A pose with a quaternion ``scale`` times unit length (the renderers normalise it, the model keeps it)."""
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    q = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), math.sin(angle / 2) * a]) * scale
    return torch.cat([torch.tensor([tx, ty, tz], dtype=torch.float64), q])[None]


@pytest.mark.parametrize("pose", [
    _pose(0.0, 0.0, 0.45, 0.4),
    _pose(0.04, -0.03, 0.6, 2.0, scale=1.0003),  # not quite unit
    _pose(0.15, 0.1, 0.5, -1.0),  # the window cut by the frame's corner
])
def test_the_binding_is_the_stage_calls_bit_for_bit(renderer, pose):
    radius = _radius(renderer)
    got = render_model(renderer, pose, radius, margin_px=10)
    win = render_window(pose, CAM, radius, margin_px=10)
    u0, v0, w, h = win[0].tolist()
    u1, v1 = min(max(u0, 0), CAM.width - min(w, CAM.width)), min(max(v0, 0), CAM.height - min(h, CAM.height))
    w, h = min(w, CAM.width), min(h, CAM.height)  # clipped to the frame as the tracker renders
    assert got.window.tolist() == [[u1, v1, w, h]]
    want = renderer.render(pose, roi=(u1, v1, w, h))
    assert torch.equal(got.depth, want.depth) and torch.equal(got.gray, want.gray)
    assert float(want.depth.max()) > 0  # the comparison covers real pixels
    model = template_model(pose.float().double(), want.depth, want.gray, torch.tensor([[u1, v1]]), CAM,
                           canvas=OPTIONS["canvas"], margin_px=OPTIONS["box_margin_px"],
                           edge_clip=OPTIONS["edge_clip"], silhouette=OPTIONS["silhouette"],
                           interior=OPTIONS["interior"])
    for name, a, c in zip(model._fields, got.model, model):
        assert a.dtype == c.dtype and torch.equal(a, c), name
    assert float(model.render_template.abs().max()) > 0


def test_the_observation_box_is_the_models_float32_box(renderer):
    """The tracker observes the EROS under ``observed_box``, which the compiled call writes: the model's box."""
    bind = RenderModelBinding(renderer, _radius(renderer), margin_px=10, **OPTIONS)
    got = bind(_pose(0.0, 0.0, 0.45, 0.4).numpy(), True, True)
    assert got.model.box.dtype == torch.float32
    assert torch.equal(torch.from_numpy(bind.observed_box), got.model.box.double())
    again = bind(_pose(0.03, 0.01, 0.5, 0.2).numpy(), True, True)  # each model made rewrites it
    assert torch.equal(torch.from_numpy(bind.observed_box), again.model.box.double())
    assert not torch.equal(got.model.box, again.model.box)


def test_the_render_alone(renderer):
    pose = _pose(0.0, 0.01, 0.5, 0.7)
    depth_only = render_model(renderer, pose, _radius(renderer), shaded=False, model=False)
    shaded = render_model(renderer, pose, _radius(renderer), model=False)
    assert depth_only.gray is None and depth_only.model is None and shaded.model is None
    assert torch.equal(depth_only.depth, shaded.depth) and shaded.gray is not None


def test_a_textured_mesh_renders_its_texture_into_the_template():
    """The tracker's fused render of a printed mesh equals the rasteriser's textured render, and its template has the
    print's inner edges (the oracle: the renderer's own render and template_model of it)."""
    from torchevtrack.synth.texture import printed_texture

    pose = _pose(0.0, 0.0, 0.45, 0.4)
    plain = RasterRenderer(load_mesh("box"), CAM, background=0.25)
    printed = RasterRenderer(printed_texture(load_mesh("box"), seed=3), CAM, background=0.25)
    radius = _radius(printed)
    energy, gradient = [], []
    for r in (plain, printed):
        got = render_model(r, pose, radius, margin_px=10, interior=0.0)  # the edges alone
        u0, v0, w, h = got.window[0].tolist()
        want = r.render(pose, roi=(u0, v0, w, h))
        assert torch.equal(got.gray, want.gray)
        energy.append(float(got.model.render_template.abs().sum()))
        gradient.append(float(got.gray.diff(dim=1).abs().sum() + got.gray.diff(dim=2).abs().sum()))
        r.close()
    assert gradient[1] > 1.5 * gradient[0]  # the print's edges in the render
    assert energy[1] > 1.1 * energy[0]  # and in the template built from it


@pytest.mark.parametrize("canvas", [12, 16])
def test_a_window_of_several_canvases_is_rendered_at_its_scale(renderer, canvas):
    """A window of 1.5 canvases or more is rendered ``s = (min(w, h) + canvas) // (2 canvas)`` times smaller. The
    oracle: the renderer's render of the frame of a camera ``s`` times smaller that sees that window, and
    ``template_model`` of it; the depth handed out repeats each of its pixels over ``s x s`` frame pixels, and the
    box and gain are given in frame pixels."""
    pose = _pose(0.01, -0.01, 0.4, 0.6)
    radius = _radius(renderer)
    got = render_model(renderer, pose, radius, margin_px=10, canvas=canvas)
    u0, v0, w, h = got.window[0].tolist()
    s = (min(w, h) + canvas) // (2 * canvas)
    assert s >= 2, (w, h)
    fx, fy, cx, cy = CAM.fx / s, CAM.fy / s, (CAM.cx + 0.5) / s - 0.5, (CAM.cy + 0.5) / s - 0.5
    small = RasterRenderer(load_mesh("can"), Camera(-(-w // s), -(-h // s), fx, fy, cx - u0 / s, cy - v0 / s),
                           background=0.25)
    want = small.render(pose)
    small.close()
    repeated = want.depth[0].repeat_interleave(s, 0).repeat_interleave(s, 1)[:h, :w]
    assert torch.equal(got.depth[0], repeated) and float(repeated.max()) > 0
    assert got.gray is None  # only the model reads the grey image
    options = dict(canvas=canvas, edge_clip=OPTIONS["edge_clip"], silhouette=OPTIONS["silhouette"],
                   interior=OPTIONS["interior"])
    origin = torch.tensor([[u0 / s, v0 / s]], dtype=torch.float64)
    frame = Camera(CAM.width // s, CAM.height // s, fx, fy, cx, cy)
    model = template_model(pose.float().double(), want.depth, want.gray, origin, frame,
                           margin_px=OPTIONS["box_margin_px"] / s, **options)
    for name in ("K", "render_template", "coef", "depth", "points", "valid", "interior", "pose", "render_pose"):
        a, c = getattr(got.model, name), getattr(model, name)
        assert a.dtype == c.dtype and torch.equal(a, c), name
    box, gain = render_box(want.depth.numpy(), origin.numpy(), camera_array(frame), OPTIONS["box_margin_px"] / s)
    frame_box = torch.tensor([(box[0, 0] + 0.5) * s - 0.5, (box[0, 1] + 0.5) * s - 0.5, box[0, 2] * s])
    assert torch.equal(got.model.box[0], frame_box.float())
    assert torch.equal(got.model.gain, torch.from_numpy(gain) * s)
