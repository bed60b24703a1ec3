"""The tracker's fused steps: several stages' compiled pieces in one call that releases the GIL.

An update's small per-element operations cost less as one compiled call than as stage calls with tensor glue between
them, and on the tracker's threads a call that holds the GIL delays the other thread. Each fused step here is built
from the stages' public compiled pieces (their ``arrays()`` records, ``*_step`` and ``*_kernel`` functions), runs on
numpy views of their buffers, unchecked but for the events, and gives exactly the numbers of the stage calls one after
the other (``tests/test_intake.py``, ``tests/test_motion.py``, ``tests/test_render_model.py``,
``tests/test_correction.py``, ``tests/test_output.py``):

- :func:`bind_intake`, step 1: a window's events into the :class:`~torchevtrack.stages.eros.EROS`, its
  :class:`~torchevtrack.stages.eros.TimeSurface` and the :class:`~torchevtrack.stages.flow.TripletFlow`. Each reads
  only its own state and the events, so their order does not matter: the flow (which checks every event before it
  writes), then the EROS and the time surface.
- :func:`motion`, steps 2-3: the twist and the propagated pose of every element. With ``source = "flow"`` (the
  paper) the velocity filter's step (:func:`~torchevtrack.stages.velocity.velocity_step`: predict, the slow valid
  flow vectors, their depth from the last render, update about the object centre, plus the correction feedback,
  back about the camera); ``"poses"``: :func:`~torchevtrack.stages.propagate.twist_between` the last two poses;
  ``"none"``: zero twist. Then :func:`~torchevtrack.stages.propagate.propagate_step` by ``dt``, which keeps the pose
  with zero twist where the prediction is not valid.
- :class:`RenderModelBinding`, steps 4-5's render and template model of one pose: the window
  (:func:`~torchevtrack.stages.template.window_of`), the compiled rasteriser's render in it
  (:func:`~torchevtrack.raster.rasterise`) and the template model of that render
  (:func:`~torchevtrack.stages.template.template_model`) at the pose's float32 rounding. One call without the GIL:
  with ``render.ahead`` the tracker's pipeline thread makes the next update's render and model while the calling
  thread searches, and as separate calls that job would hold the GIL between its kernels.
- :func:`bind_correction`, step 5: the canvas box of the render's extent, the observation under it
  (:func:`~torchevtrack.stages.eros.canvas_observation`), then the rest of the template model and the search
  (:func:`~torchevtrack.stages.template.newton_arrays`; the ablation's argmax and group rules through
  :func:`~torchevtrack.stages.template.correct_canvas`). Once the observation is made it tells the caller
  (``on_observed``): the next window's events may then update the surfaces while the model and the search run.
- :func:`output`, step 6: the correction's rate into the
  :class:`~torchevtrack.stages.velocity.CorrectionFeedback` (:func:`~torchevtrack.stages.propagate.twist_between`
  the predicted and measured poses about the predicted centre, :func:`~torchevtrack.stages.velocity.feedback_step`),
  the :class:`~torchevtrack.stages.ukf.PoseUKF` predict and update (:func:`~torchevtrack.stages.ukf.ukf_step`; its
  pose is the output, without it the measured pose), the current pose where the output is not valid, and canonical
  quaternions (``w >= 0``, :func:`~torchevtrack.geometry.quat_canonical`).
- :func:`watch`, after step 6 (with ``config.loss``): the :class:`~torchevtrack.loss.LossDetector`'s rule on the
  update's quality (:func:`~torchevtrack.loss.loss_step`) and, with ``config.recover``, the
  :class:`~torchevtrack.recover.Recoverer`'s books (:func:`~torchevtrack.recover.recover_step`): what the caller must
  do in Python (a callback, a search) is rare, the books are every update.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import nb_normalise_quaternions
from torchevtrack.kernels import kernel
from torchevtrack.loss import LossArrays, loss_step
from torchevtrack.raster import AMBIENT, LIGHT_DIRECTION, RasterRenderer, render_kernel
from torchevtrack.recover import RecoverArrays, recover_step
from torchevtrack.stages.eros import (EROS, RecencyArrays, TimeSurface, canvas_kernel, eros_kernel, prepare_events,
                                      time_kernel)
from torchevtrack.stages.flow import FlowField, TripletFlow, event_arrays, events_in_range, flow_packet, range_error
from torchevtrack.stages.propagate import propagate_kernel, propagate_step, twist_between_kernel, valid_pose
from torchevtrack.stages.template import (Correction, TemplateModel, box_kernel, camera_array, correct_canvas,
                                          model_filters, model_in_box, model_kernel, newton_arrays, render_box,
                                          render_scale, window_kernel)
from torchevtrack.stages.ukf import UKFArrays, ukf_step
from torchevtrack.stages.velocity import FeedbackArrays, KFArrays, feedback_step, shift_twist_kernel, velocity_step

__all__ = ["CorrectionStep", "MotionArgs", "OutputArgs", "RenderModelBinding", "Rendered", "bind_correction",
           "bind_intake", "motion", "output", "render_ahead", "watch"]


def bind_intake(eros: EROS, time_surface: TimeSurface | None, flow: TripletFlow,
                rows: slice | None = None) -> Callable[..., FlowField]:
    """Step 1 bound to the stages' buffers (numpy views of their ``rows``, default all ``B``, written in place at each
    call); ``time_surface`` ``None``: none is kept.

    Returns ``run(x, y, t, p, b, surfaces=True, checked=None)``: ``eros(x, y, b, rows)``, ``time_surface(x, y, t, b,
    rows)`` and ``flow(x, y, t, p, b, rows)`` in one compiled call, with the arguments and errors of the stages'
    ``forward`` (packed events: ``(N,)`` integer pixels ``x, y``, int64 microseconds ``t``, polarity ``p``, batch
    index ``b`` counted from the first of ``rows``); on an error nothing is written. It gives the flow's
    :class:`~torchevtrack.stages.flow.FlowField` as numpy arrays. With ``surfaces=False`` it runs the flow alone,
    leaving the EROS and the time surface to the caller. ``checked``, if given, is called with the events as numpy
    arrays ``(x, y, t, b)`` (``b`` ``None`` for one element) once every event is known to be in range, before
    anything is written (from there on the call cannot fail): the caller may start taking them into the EROS and the
    time surface elsewhere then (:func:`~torchevtrack.stages.eros.bind_observe`).
    """
    surface = eros.surface if rows is None else eros.surface[rows]
    sae = flow.sae_padded if rows is None else flow.sae_padded[rows]
    seen = flow.last_padded if rows is None else flow.last_padded[rows]
    B, C = sae.shape[:2]
    times = time_surface is not None
    last = (time_surface.last_us if rows is None else time_surface.last_us[rows]) if times else \
        torch.empty(B, 0, 0, dtype=torch.int64)
    if surface.shape[0] != B or last.shape[0] != B:
        raise ValueError(f"the EROS, the time surface and the flow must hold the same elements, got "
                         f"{surface.shape[0]}, {last.shape[0]} and {B}")
    G = flow.n_blocks
    s, last_np, sae_np, seen_np = surface.numpy(), last.numpy(), sae.numpy(), seen.numpy()
    lam, r = s.dtype.type(eros.lam), eros.kernel_size // 2
    matching = flow.params

    def _range_errors(x, y, t, p, b):
        prepare_events(x, y, b, *surface.shape[1:], B)  # the EROS stage's range error
        range_error(tuple(sae.shape[:2]) + (flow.height, flow.width), x, y, t, p, b)  # the flow's (polarity)

    def run(x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None = None,
            b: torch.Tensor | None = None, surfaces: bool = True,
            checked: Callable[..., object] | None = None) -> FlowField:
        xn, yn, tn, pn, bn, batched = event_arrays(C, x, y, t, p, b)  # checks the fields as the EROS stage does
        if checked is not None:
            if not events_in_range(xn, yn, pn, bn, C, batched, B, flow.height, flow.width):
                _range_errors(x, y, t, p, b)
            checked(xn, yn, tn, bn if batched else None)
        out, uv = np.zeros((B, G, 2), dtype=np.float32), np.empty((B, G, 2), dtype=np.float32)
        valid, count = np.empty((B, G), dtype=np.bool_), np.empty((B, G), dtype=np.int64)
        if not _intake_kernel(s, lam, r, last_np, surfaces, surfaces and times, sae_np, seen_np, xn, yn, tn, pn, bn, C,
                              batched, *matching, out, uv, valid, count):
            _range_errors(x, y, t, p, b)
        return FlowField(uv, out, valid, count)
    return run


@kernel
def _intake_kernel(surface, lam, r, last, surfaces, times, sae, seen, x, y, t, p, b, C, batched, dirs, pad, dt_max_us,
                   tol, onset_us, chunk, block_x, block_y, G, min_samples, max_candidates, tie_tol, normal, inlier,
                   fill, out, uv, valid, count):
    """:func:`~torchevtrack.stages.flow.flow_packet`, then (``surfaces``) :func:`~torchevtrack.stages.eros.eros_kernel`
    and (``times``) :func:`~torchevtrack.stages.eros.time_kernel` if every event was in range (False: nothing
    written)."""
    ok = flow_packet(sae, seen, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, onset_us, chunk, block_x, block_y,
                     G, min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv, valid, count)
    if ok and surfaces and x.shape[0]:
        ok = eros_kernel(surface, x, y, b, batched, r, lam) and (not times or time_kernel(last, x, y, t, b, batched))
    return ok


class MotionArgs(NamedTuple):
    """What :func:`motion` reads besides the flow and the render (numpy views, read at each call): ``source``
    (``"flow"``, ``"poses"`` or ``"none"``, as ``velocity.source`` of the config), the current and previous poses
    ``(B, 7)`` float64, the period ``dt`` ``(B,)`` s (:func:`~torchevtrack.stages.periods`) and ``min_depth`` ``(B,)``
    float64, the nearest valid object-centre depth (m); for ``source = "flow"`` the velocity filter's
    :class:`~torchevtrack.stages.velocity.KFArrays` (:meth:`~torchevtrack.stages.velocity.VelocityKF.arrays`; else
    ``None``), the speed ``max_speed`` (px/s) from which a flow vector is dropped, the radius (px) of
    :func:`~torchevtrack.stages.velocity.sample_depth` and the feedback twist ``(B, 6)`` about the centre added to the
    filter's (or ``None``)."""

    source: str
    pose: np.ndarray
    prev_pose: np.ndarray
    dt: np.ndarray
    min_depth: np.ndarray
    kf: KFArrays | None = None
    max_speed: float = float("inf")
    radius: int = 2
    feedback: np.ndarray | None = None


def motion(a: MotionArgs, field: FlowField | None = None, depth: np.ndarray | None = None,
           origin: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Steps 2-3 (see the module docstring) in one compiled call, unchecked: the twist and the propagated pose of
    every element; with ``source = "flow"`` the filter of ``a.kf`` is updated in place.

    Args:
        a: the bound arguments (:class:`MotionArgs`).
        field, depth, origin: for ``source = "flow"``: the flow field ``(B, G)`` as numpy arrays
            (:func:`bind_intake`), the last render's depth ``(B, h, w)`` float32 and its top-left pixel ``(B, 2)``
            int64.

    Returns:
        New arrays ``(predicted, twist, n_vectors, rejected)``: the propagated poses ``(B, 7)`` float64
        ``[t (m), q (w, x, y, z)]``, the camera-frame twist ``(B, 6)`` float64 ``[v (m/s), w (rad/s)]`` they were
        propagated with, the flow vectors the filter weighed ``(B,)`` int64 (0 unless ``source = "flow"``) and
        ``(B,)`` bool where the prediction was not valid and the pose was kept with zero twist.

    Raises:
        torch.linalg.LinAlgError: a velocity filter's covariance is not positive definite.
    """
    B = a.pose.shape[0]
    out = np.empty((B, 7)), np.empty((B, 6)), np.zeros(B, dtype=np.int64), np.empty(B, dtype=np.bool_)
    kf = a.kf if a.source == "flow" else None
    bad = _motion_kernel(a.source == "poses", a.pose, a.prev_pose, a.dt, a.min_depth, kf, field, depth, origin,
                         float(a.max_speed), int(a.radius), a.feedback, *out)
    if bad >= 0:
        raise torch.linalg.LinAlgError(f"kf_update: the covariance of filter {bad} is not positive-definite")
    return out


@kernel
def _motion_kernel(from_poses, pose, prev_pose, dt, min_depth, kf, field, depth, origin, max_speed, radius, feedback,
                   predicted, twist, n_vectors, rejected):
    """:func:`motion` (``kf`` ``None``: the twist of the last two poses, ``from_poses``, or zero). Returns -1, or the
    index of a velocity filter whose covariance is not positive definite."""
    if kf is not None:
        bad = velocity_step(kf, field, depth, origin, max_speed, radius, dt, pose[:, :3].copy(), feedback, twist,
                            n_vectors)
        if bad >= 0:
            return bad
    elif from_poses:
        twist_between_kernel(prev_pose, pose, dt, twist)
    else:
        twist[:] = 0.0
    propagate_step(pose, twist, dt, min_depth, predicted, rejected)
    return -1


@kernel
def render_ahead(predicted, twist, dt, min_depth, ahead, ahead_ok, now, now32):
    """The tracker's ``render.ahead`` poses, row by row: ``now`` (float64 and ``now32`` float32) is ``ahead`` where
    ``ahead_ok`` (the last update's poses for this one), else ``predicted``; then ``ahead`` becomes ``predicted``
    moved on by ``twist`` for ``dt`` (:func:`~torchevtrack.stages.propagate.propagate`) and ``ahead_ok`` whether
    that is a valid pose (the next update's).

    Shape: ``predicted (B, 7)``, ``twist (B, 6)``, ``dt, min_depth (B,)``; ``ahead (B, 7)``, ``ahead_ok (B,)`` in and
    out; ``now, now32 (B, 7)`` out.
    """
    for b in range(predicted.shape[0]):
        src = ahead[b] if ahead_ok[b] else predicted[b]
        for j in range(7):
            now[b, j] = src[j]
            now32[b, j] = np.float32(src[j])
    propagate_kernel(predicted, twist, dt, ahead)
    for b in range(predicted.shape[0]):
        ahead_ok[b] = valid_pose(ahead[b], min_depth[b])


class Rendered(NamedTuple):
    """A render of one pose in its window and, if asked for, its template model (:class:`RenderModelBinding`).

    Attributes:
        depth: ``(1, h, w)`` float32 metres (0 off the object); gray: ``(1, h, w)`` float32 or ``None`` (unshaded, or
            a model made from a render at a scale: :class:`RenderModelBinding`).
        window: ``(1, 4)`` int64 ``(u0, v0, w, h)`` of the frame.
        model: the :class:`~torchevtrack.stages.template.TemplateModel` of the render, or ``None``.
    """

    depth: torch.Tensor
    gray: torch.Tensor | None
    window: np.ndarray
    model: TemplateModel | None


@kernel
def _render_model_kernel(pose, radius, cam, W, H, margin, vertices, faces, planes, albedo, normals, znear, zfar, light,
                         ambient, background, shaded, model, box_margin, silhouette, edge_scale, interior, g1, g2, pre, N,
                         step, P, observed_box, texture):
    """:class:`RenderModelBinding`'s compiled call: the window of ``pose`` (``(1, 4)``), its render there at its
    normalised copy (the renderers' rule), its float32 rounding ``pose32`` (the model's pose), and with ``model`` the
    template model's arrays at ``pose32`` (``box, K, gain, render_template, depth, coef, points, valid,
    interior``), its box also into ``observed_box`` as float64. ``texture``: the mesh's
    :class:`~torchevtrack.raster.RasterTexture` as a tuple, or ``None`` (untextured).

    With ``model`` the window is rendered at :func:`~torchevtrack.stages.template.render_scale` ``s`` (the model is
    that of the frame of a camera ``s`` times smaller, its box and gain given in frame pixels) and the depth handed
    out is that render's, each pixel repeated over its ``s x s`` frame pixels; the grey image is then not handed
    out (empty)."""
    unit = pose.copy()
    nb_normalise_quaternions(unit, np.empty(1))
    pose32 = pose.astype(np.float32).astype(np.float64)
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    win = np.empty((1, 4), dtype=np.int64)
    window_kernel(np.ascontiguousarray(pose[:, :3]), radius, fx, fy, cx, cy, margin, W, H, True, win)
    u0, v0, w, h = win[0, 0], win[0, 1], win[0, 2], win[0, 3]
    s = render_scale(w, h, N) if model else 1
    depth = np.empty((1, h, w), dtype=np.float32)
    origin = win[:, :2].astype(np.float64)
    if s == 1:
        rendered, sub, sub_origin = depth, cam, origin
    else:  # the frame of a camera s times smaller
        rendered = np.empty((1, -(-h // s), -(-w // s)), dtype=np.float32)
        sub = np.array([fx / s, fy / s, (cx + 0.5) / s - 0.5, (cy + 0.5) / s - 0.5])
        sub_origin = origin / s
    gray = np.empty(rendered.shape if shaded else (1, 0, 0), dtype=np.float32)
    render_kernel(vertices, faces, planes, albedo, normals, unit, sub[0], sub[1], sub[2] - sub_origin[0, 0],
                  sub[3] - sub_origin[0, 1], znear, zfar, light, ambient, background, rendered, gray, texture)
    if s > 1:
        _repeat_pixels(rendered[0], s, depth[0])
    box = np.empty((1, 3))
    gain = np.empty(1, dtype=np.float32)
    box32, K = np.empty((1, 3), dtype=np.float32), np.empty((1, 4), dtype=np.float32)
    n, m = (N, P) if model else (0, 0)  # without the model: empty arrays (a render alone allocates nothing more)
    T, Z = np.empty((1, n, n), dtype=np.float32), np.empty((1, n, n), dtype=np.float32)
    coef = np.zeros((1, n + 6, n + 6) if model else (1, 0, 0), dtype=np.float32)
    points, valid = np.empty((1, m, 3), dtype=np.float32), np.empty((1, m), dtype=np.bool_)
    if model:
        box_kernel(rendered, sub_origin, sub, box_margin / s, box, gain)
        model_kernel(rendered, gray, sub_origin, box, sub, np.ascontiguousarray(pose32[:, 2]), np.bool_(True),
                     silhouette, edge_scale, interior, g1, g2, pre, step, step, box32, K, T, coef, Z, points, valid)
        if s > 1:  # the box and the gain in frame pixels (K is the same in either)
            box32[0, 0] = (box[0, 0] + 0.5) * s - 0.5
            box32[0, 1] = (box[0, 1] + 0.5) * s - 0.5
            box32[0, 2] = box[0, 2] * s
            gain[0] *= s
            gray = np.empty((1, 0, 0), dtype=np.float32)
        for k in range(3):
            observed_box[0, k] = box32[0, k]
    return win, depth, gray, pose32, (box32, K, gain, T, Z, coef, points, valid, np.full(1, interior))


@kernel
def _repeat_pixels(small, s, out):
    """``out[v, u] = small[v // s, u // s]`` for every pixel of ``out`` ``(h, w)`` (``small`` ``(ceil(h / s),
    ceil(w / s))``): the first row of each ``s`` widened from its small row, the others copied from it (element
    loops: twice the speed of slice assignments here)."""
    h, w = out.shape
    for i in range(small.shape[0]):
        row, first = small[i], out[i * s]
        u = 0
        for j in range(small.shape[1]):
            for _ in range(min(s, w - u)):
                first[u] = row[j]
                u += 1
        for v in range(i * s + 1, min((i + 1) * s, h)):
            dst = out[v]
            for u in range(w):
                dst[u] = first[u]


class RenderModelBinding:
    """Steps 4-5's render and template model of one pose (see the module docstring), bound to a compiled rasteriser
    and the options, unchecked: for a caller whose poses are valid (finite, ``z > 0``, non-zero quaternion).

    ``binding(pose, shaded, model) -> Rendered`` renders ``pose`` ``(1, 7)`` float64 (object in the camera frame;
    its quaternion normalised as the renderers do) in its window (:func:`~torchevtrack.stages.template.window_of`
    with ``margin_px``, clipped to the frame), the grey image too with ``shaded``, and with ``model`` (needs
    ``shaded``) the template model (:func:`~torchevtrack.stages.template.template_model` with ``canvas``,
    ``box_margin_px`` as its ``margin_px``, ``edge_clip``, ``silhouette`` and ``interior``) at the pose's float32
    rounding. A window of 1.5 canvases or more is then rendered
    :func:`~torchevtrack.stages.template.render_scale` times smaller: its model is that render's, its depth the
    render's pixels repeated, and no grey image is handed out. A caller that runs the compiled call on another
    thread without the GIL in between calls it in three parts: ``args = binding.start(pose, shaded, model)`` (the
    Python part before it), ``raw = binding.kernel(*args)`` (the compiled call) and ``binding.finish(raw)``.

    Args:
        renderer: the object's :class:`~torchevtrack.raster.RasterRenderer` (its camera is the frame's).
        radius: the object's bounding radius (metres).

    Attributes:
        observed_box: ``(1, 3)`` float64, the canvas box of the last model made (its float32 box, under which the
            observation is made), written by the compiled call.

    Example:
        >>> import torch
        >>> from torchevtrack.camera import Camera
        >>> from torchevtrack.mesh import load_mesh
        >>> from torchevtrack.raster import RasterRenderer
        >>> r = RasterRenderer(load_mesh("can"), Camera(64, 48, 50.0, 50.0, 32.0, 24.0))
        >>> bind = RenderModelBinding(r, 0.06, margin_px=24, canvas=32, box_margin_px=20.0, edge_clip=0.1,
        ...                           silhouette=True, interior=1.0)
        >>> out = bind(torch.tensor([[0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).numpy(), True, True)
        >>> out.window.tolist(), tuple(out.model.coef.shape)
        ([[0, 0, 64, 48]], (1, 38, 38))
    """

    kernel = staticmethod(_render_model_kernel)  # the compiled call

    def __init__(self, renderer: RasterRenderer, radius: float, *, margin_px: int, canvas: int,
                 box_margin_px: float, edge_clip: float, silhouette: bool, interior: float) -> None:
        mesh, cam = renderer.raster_mesh, renderer.camera
        self.observed_box = np.zeros((1, 3))
        step = max(1, canvas // 16)  # the model's object points: every step-th canvas pixel
        points = len(range(step // 2, canvas, step)) ** 2
        texture = renderer.raster_texture
        self._args = (np.full(1, float(radius)), np.array([cam.fx, cam.fy, cam.cx, cam.cy]), cam.width, cam.height,
                      float(margin_px), *mesh, renderer.znear, renderer.zfar, LIGHT_DIRECTION, AMBIENT,
                      renderer.background)
        self._model_args = (float(box_margin_px), silhouette, 0.125 / edge_clip, float(interior), *model_filters(canvas),
                            canvas, step, points, self.observed_box, None if texture is None else tuple(texture))

    def __call__(self, pose: np.ndarray, shaded: bool, model: bool) -> Rendered:
        return self.finish(self.kernel(*self.start(pose, shaded, model)))

    def start(self, pose: np.ndarray, shaded: bool, model: bool) -> tuple:
        """The arguments of :attr:`kernel` for ``pose``."""
        return pose, *self._args, shaded, model, *self._model_args

    @staticmethod
    def finish(raw: tuple) -> Rendered:
        """The :class:`Rendered` of :attr:`kernel`'s result (a window has pixels, so an empty grey image means an
        unshaded render, and empty model arrays a render without its model)."""
        win, depth, gray, pose32, made = raw
        made_model = None
        if made[3].size:  # the template
            p = torch.from_numpy(pose32)
            made_model = TemplateModel(p, p, *(torch.from_numpy(a) for a in made))
        return Rendered(torch.from_numpy(depth), torch.from_numpy(gray) if gray.size else None, win, made_model)


class CorrectionStep(NamedTuple):
    """Result of :func:`bind_correction`'s ``run``: the template ``model`` of the render (or the one given) and the
    ``correction`` of the predicted poses, as :func:`~torchevtrack.stages.template.newton_arrays` (or
    :func:`~torchevtrack.stages.template.correct_canvas` for the other rules) returns it, its fields as numpy
    arrays."""

    model: TemplateModel
    correction: Correction


def bind_correction(surface: np.ndarray, last_us: np.ndarray, camera: Camera, *, canvas: int, margin_px: float,
                    edge_clip: float, silhouette: bool, interior: float, dp_px: float, dtheta_deg: float, rule: str,
                    iterations: int, max_dz: float, max_age_us: int,
                    recency: RecencyArrays) -> Callable[..., CorrectionStep]:
    """Step 5 (see the module docstring) bound to the EROS ``surface`` ``(B, H, W)`` float32 and the time surface
    ``last_us`` ``(B, C, H, W)`` int64 (numpy views, read at each call) and the options, unchecked.

    Options: ``canvas, margin_px, edge_clip, silhouette, interior`` as for
    :func:`~torchevtrack.stages.template.template_model`; ``dp_px, dtheta_deg, rule, iterations, max_dz`` as for
    :func:`~torchevtrack.stages.template.correct_canvas`; ``max_age_us`` as for
    :func:`~torchevtrack.stages.eros.canvas_observation`; ``recency`` the elements' recency windows
    (:meth:`~torchevtrack.stages.eros.Recency.arrays`, read at each call).

    Returns ``run(render_pose, predicted, depth, gray, origin, t_now_us, model=None, on_observed=None, obs=None,
    z_ref=None)``
    of numpy arrays: the render ``depth`` ``(B, h, w)`` float32 made at ``render_pose`` ``(B, 7)`` float32, its grey
    image ``gray`` (or ``None``: silhouette only), its window's top-left pixel ``origin`` ``(B, 2)`` int64, the start
    poses ``predicted`` ``(B, 7)`` float64 and ``t_now_us`` ``(B,)`` int64; or ``render_pose``, ``depth``, ``gray``,
    ``origin`` ``None`` with the ``model`` of an earlier render to reuse. ``on_observed`` is called (no arguments) once
    the observation is made: ``surface`` and ``last_us`` are not read after that. ``obs``: the observation
    ``(B, N, N)`` float32 under the ``model``'s box if it was made elsewhere
    (:func:`~torchevtrack.stages.eros.bind_observe`); the surfaces are then not read. ``run`` gives the
    :class:`CorrectionStep`, equal to ``template_model``, ``canvas_observation`` under the model's box and
    ``newton_search`` (or ``correct_canvas``) one after the other. ``z_ref`` ``(B,)`` float64: the centres of the
    depth bands of width ``2 max_dz`` (``None``: the predicted depths).
    """
    cam = camera_array(camera)
    max_age_us = int(max_age_us)
    dp, dtheta = float(dp_px), math.radians(dtheta_deg)

    def run(render_pose, predicted, depth, gray, origin, t_now_us, model=None, on_observed=None,
            obs=None, z_ref=None) -> CorrectionStep:
        B = predicted.shape[0]
        if model is None:  # the canvas box first: the observation needs only that, the rest of the model can wait
            origin64 = origin.astype(np.float64)
            box, gain = render_box(depth, origin64, cam, margin_px)
            N, observed_box = canvas, box.astype(np.float32).astype(np.float64)  # as the model's box (float32) gives it
        else:
            N = model.depth.shape[-1]
        if obs is None:
            obs = np.empty((B, N, N), dtype=np.float32)
            canvas_kernel(surface, last_us, observed_box if model is None else model.box.numpy().astype(np.float64),
                          t_now_us.astype(np.int64, copy=False), max_age_us, *recency, obs)
        if on_observed is not None:
            on_observed()
        if model is None:
            model = model_in_box(render_pose.astype(np.float64), depth, depth if gray is None else gray,
                                 gray is not None, origin64, cam, box, gain, N, edge_clip, silhouette, interior)
        if rule != "newton":
            c = correct_canvas(model, torch.from_numpy(predicted), torch.from_numpy(obs), camera, dp_px=dp_px,
                               dtheta_deg=dtheta_deg, rule=rule, iterations=iterations, max_dz=max_dz,
                               z_ref=None if z_ref is None else torch.from_numpy(z_ref))
            return CorrectionStep(model, Correction(*(f.numpy() for f in c)))
        c = newton_arrays(model, predicted, obs, camera.fx, camera.fy, dp, dtheta, iterations, max_dz, z_ref)
        return CorrectionStep(model, c)
    return run


class OutputArgs(NamedTuple):
    """What :func:`output` reads besides the update's poses (numpy views, read at each call): the current (last output)
    pose ``(B, 7)`` float64, the period ``dt`` ``(B,)`` s, ``min_depth`` ``(B,)`` float64 m, ``depth_lag`` ``(B,)``
    float64 m (written: the measured depth less the output's, 0 where the output was rejected), the UKF's
    :class:`~torchevtrack.stages.ukf.UKFArrays` (``None``: the measured poses are the output) and the feedback's
    :class:`~torchevtrack.stages.velocity.FeedbackArrays` (``None``: none)."""

    pose: np.ndarray
    dt: np.ndarray
    min_depth: np.ndarray
    depth_lag: np.ndarray
    ukf: UKFArrays | None = None
    feedback: FeedbackArrays | None = None


def output(a: OutputArgs, predicted: np.ndarray, measured: np.ndarray, twist: np.ndarray,
           symmetry_axis: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Step 6 (see the module docstring) in one compiled call, unchecked: the output poses of an update; the UKF and
    the feedback of ``a`` are updated in place.

    Args:
        a: the bound arguments (:class:`OutputArgs`).
        predicted, measured: ``(B, 7)`` float64 propagated and corrected poses; twist: ``(B, 6)`` float64 ``[v, w]``
            of the propagation.
        symmetry_axis: ``(B, 3)`` float64 camera-frame unit axes the feedback ignores turns about (zero rows: none),
            or ``None``.

    Returns:
        New arrays ``(pose, rejected)``: the output poses ``(B, 7)`` float64 with canonical quaternions and ``(B,)``
        bool where the output was not valid and the current pose was kept.

    Raises:
        torch.linalg.LinAlgError: a UKF covariance is not positive definite.
    """
    B = a.pose.shape[0]
    out, rejected = np.empty((B, 7)), np.empty(B, dtype=np.bool_)
    bad = _output_kernel(a.pose, predicted, measured, twist, a.dt, a.min_depth, a.feedback, symmetry_axis, a.ukf, out,
                         rejected, a.depth_lag)
    if bad >= 0:
        raise torch.linalg.LinAlgError(f"{'ukf_predict' if bad < B else 'ukf_update'}: the covariance of "
                                       f"filter {bad % B} is not positive-definite")
    return out, rejected


@kernel
def _output_kernel(pose, predicted, measured, twist, dt, min_depth, feedback, axis, ukf, out, rejected, depth_lag):
    """:func:`output` into ``out``, ``rejected``, ``depth_lag``. Returns -1, or the failing UKF filter (see
    :func:`~torchevtrack.stages.ukf.ukf_step`)."""
    if feedback is not None:
        B = pose.shape[0]
        rate, rate_c = np.empty((B, 6)), np.empty((B, 6))
        twist_between_kernel(predicted, measured, dt, rate)
        shift_twist_kernel(rate, predicted[:, :3].copy(), rate_c)  # about the predicted centre
        feedback_step(feedback, rate_c, axis)
    if ukf is not None:
        bad = ukf_step(ukf, dt, twist, measured)
        if bad >= 0:
            return bad
        out[:] = ukf.x[:, 6:13]
    else:
        out[:] = measured
    for i in range(pose.shape[0]):
        rejected[i] = not valid_pose(out[i], min_depth[i])
        depth_lag[i] = 0.0 if rejected[i] else measured[i, 2] - out[i, 2]
        if rejected[i]:
            out[i] = pose[i]
            if ukf is not None:
                ukf.x[i, 6:13] = pose[i]
        q0, q1, q2, q3 = out[i, 3], out[i, 4], out[i, 5], out[i, 6]  # quat_canonical: the same sum of squares
        norm = max(np.sqrt(((q0 * q0 + q1 * q1) + q2 * q2) + q3 * q3), 1e-12)
        sign = -1.0 if q0 / norm < 0 else 1.0
        for j in range(3, 7):
            out[i, j] = sign * (out[i, j] / norm)
    return -1


def watch(loss: LossArrays, recover: RecoverArrays | None, score: np.ndarray, flow_vectors: np.ndarray,
          rejected: np.ndarray, burst: np.ndarray | None, t_us: np.ndarray, period_us: int,
          pose: np.ndarray) -> tuple[bool, bool]:
    """The loss rule and the re-localiser's books after an update (module docstring), in one compiled call,
    unchecked; the records are updated in place.

    Args:
        loss: the detector's :meth:`~torchevtrack.loss.LossDetector.arrays`; recover: the re-localiser's
            :meth:`~torchevtrack.recover.Recoverer.arrays` (``None``: none).
        score: ``(B,)`` the template scores (NaN: none); flow_vectors: ``(B,)`` int64; rejected, burst: ``(B,)`` bool
            (``burst`` ``None``: no burst guard); t_us: ``(B,)`` int64 the update's times; period_us: the tracker's
            window (us); pose: ``(B, 7)`` float64 the update's output poses.

    Returns:
        ``(newly_lost, search)``: an element became lost (``loss.newly_lost``), a search is due
        (:meth:`~torchevtrack.recover.Recoverer.search`).
    """
    burst = np.zeros(score.shape[0], np.bool_) if burst is None else burst
    return _watch_kernel(loss, recover, score, flow_vectors, rejected, burst, t_us, np.int64(period_us), pose)


@kernel
def _watch_kernel(loss, recover, score, flow_vectors, rejected, burst, t_us, period_us, pose):
    """:func:`watch`'s compiled body."""
    newly = loss_step(loss, score, flow_vectors, rejected, burst, t_us)
    search = False
    if recover is not None:
        search = recover_step(recover, t_us, period_us, pose, loss.newly_lost, loss.low_run, loss.patience)
    return newly, search
