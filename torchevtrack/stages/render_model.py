"""Steps 4-5's render and template model of one pose in one compiled call: the pipeline thread's job.

With ``render.ahead`` the tracker renders the next update's pose, and builds its template model, on its pipeline
thread while the calling thread searches (:class:`~torchevtrack.tracker.EventPoseTracker`). As separate calls (the
render window, the rasteriser, the canvas box, the model) that job held the GIL between its kernels, so each of its
Python steps waited for the calling thread's Python and delayed it in turn. :func:`render_model_step` runs the same
kernels in one call that releases the GIL: the window (:func:`~torchevtrack.stages.template.window_of`), the render
(:func:`~torchevtrack.raster.rasterise`) of the object in it, and with ``model`` the canvas box and the template model
(:func:`~torchevtrack.stages.template.template_model`) at the float32-rounded pose, as
:func:`~torchevtrack.stages.correction.correction_step` makes it. Its numbers are those of the separate calls bit for
bit (``tests/test_render_model.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch

from torchevtrack.geometry import _nb_normalise_quaternions
from torchevtrack.raster import AMBIENT, LIGHT_DIRECTION, RasterRenderer, _render_kernel
from torchevtrack.stages.template import TemplateModel, _box_kernel, _model_filters, _model_kernel, _window_kernel

__all__ = ["RenderModelBinding", "Rendered", "bind_render_model", "render_model_step"]


class Rendered(NamedTuple):
    """A render of one pose in its window and, if asked for, its template model.

    Attributes:
        depth: ``(1, h, w)`` float32 metres (0 off the object); gray: ``(1, h, w)`` float32 or ``None``.
        window: ``(1, 4)`` int64 ``(u0, v0, w, h)`` of the frame.
        model: the :class:`~torchevtrack.stages.template.TemplateModel` of the render, or ``None``.
    """

    depth: torch.Tensor
    gray: torch.Tensor | None
    window: np.ndarray
    model: TemplateModel | None


def render_model_step(renderer: RasterRenderer, pose: torch.Tensor, radius: float, *, margin_px: int = 24,
                      shaded: bool = True, model: bool = True, canvas: int = 128, box_margin_px: float = 20.0,
                      edge_clip: float = 0.1, silhouette: bool = True) -> Rendered:
    """Render ``pose`` ``(1, 7)`` float64 (object in the camera frame, unit-norm or not: normalised as the renderers
    do) with the compiled rasteriser in its window and, with ``model``, make its template model.

    Args:
        renderer: the object's :class:`~torchevtrack.raster.RasterRenderer` (its camera is the frame's).
        radius: the object's bounding radius (metres); margin_px: the window's margin
            (:func:`~torchevtrack.stages.template.render_window`).
        shaded: also render the grey image (needed by ``model``).
        canvas, box_margin_px, edge_clip, silhouette: as ``canvas, margin_px, edge_clip, silhouette`` of
            :func:`~torchevtrack.stages.template.template_model`.

    Shape: returns a :class:`Rendered` of one pose.

    Example:
        >>> import torch
        >>> from torchevtrack.camera import Camera
        >>> from torchevtrack.mesh import load_mesh
        >>> from torchevtrack.raster import RasterRenderer
        >>> r = RasterRenderer(load_mesh("can"), Camera(64, 48, 50.0, 50.0, 32.0, 24.0))
        >>> pose = torch.tensor([[0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        >>> out = render_model_step(r, pose, 0.06, canvas=32)
        >>> out.window.tolist(), tuple(out.model.coef.shape)
        ([[0, 0, 64, 48]], (1, 38, 38))
    """
    if not isinstance(renderer, RasterRenderer):
        raise TypeError(f"renderer must be a RasterRenderer, got {type(renderer).__name__}")
    if not isinstance(pose, torch.Tensor) or pose.shape != (1, 7) or pose.dtype != torch.float64:
        raise ValueError(f"pose must be a float64 (1, 7) tensor, got {getattr(pose, 'dtype', type(pose).__name__)} "
                         f"{tuple(getattr(pose, 'shape', ()))}")
    if not bool(torch.isfinite(pose).all()) or not float(pose[0, 2]) > 0 or not float(pose[0, 3:].norm()) > 0:
        raise ValueError("pose must be finite, with the object in front of the camera (z > 0) and a non-zero "
                         "quaternion")
    if model and not shaded:
        raise ValueError("the template model needs the grey render (shaded=True)")
    return bind_render_model(renderer, radius, margin_px=margin_px, canvas=canvas, box_margin_px=box_margin_px,
                             edge_clip=edge_clip, silhouette=silhouette)(pose.numpy(), shaded, model)


@numba.njit(cache=True, nogil=True)
def _render_model_kernel(pose, radius, cam, W, H, margin, vertices, faces, planes, albedo, normals, znear, zfar, light,
                         ambient, background, shaded, model, box_margin, silhouette, edge_scale, g1, g2, pre, N, step,
                         P, observed_box, texture):
    """The window of ``pose`` (``(1, 4)``), its render there at its normalised copy (the renderers' rule,
    :func:`~torchevtrack.render._normalise_quaternions`), its float32 rounding ``pose32`` (the model's pose, as
    correction_step rounds it), and with ``model`` the template model's arrays at ``pose32`` (``box, K, gain,
    render_template, depth, coef, points, valid``), its box also into ``observed_box`` as float64. ``texture``: the
    mesh's :class:`~torchevtrack.raster.RasterTexture` as a tuple, or ``None`` (untextured)."""
    unit = pose.copy()
    _nb_normalise_quaternions(unit, np.empty(1))
    pose32 = pose.astype(np.float32).astype(np.float64)
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    win = np.empty((1, 4), dtype=np.int64)
    _window_kernel(np.ascontiguousarray(pose[:, :3]), radius, fx, fy, cx, cy, margin, W, H, True, win)
    u0, v0, w, h = win[0, 0], win[0, 1], win[0, 2], win[0, 3]
    depth = np.empty((1, h, w), dtype=np.float32)
    gray = np.empty((1, h, w) if shaded else (1, 0, 0), dtype=np.float32)
    _render_kernel(vertices, faces, planes, albedo, normals, unit, fx, fy, cx - u0, cy - v0, znear, zfar, light,
                   ambient, background, depth, gray, texture)
    box = np.empty((1, 3))
    gain = np.empty(1, dtype=np.float32)
    box32, K = np.empty((1, 3), dtype=np.float32), np.empty((1, 4), dtype=np.float32)
    n, m = (N, P) if model else (0, 0)  # without the model: empty arrays (a render alone allocates nothing more)
    T, Z = np.empty((1, n, n), dtype=np.float32), np.empty((1, n, n), dtype=np.float32)
    coef = np.zeros((1, n + 6, n + 6) if model else (1, 0, 0), dtype=np.float32)
    points, valid = np.empty((1, m, 3), dtype=np.float32), np.empty((1, m), dtype=np.bool_)
    if model:
        origin = win[:, :2].astype(np.float64)
        _box_kernel(depth, origin, cam, box_margin, box, gain)
        _model_kernel(depth, gray, origin, box, cam, np.ascontiguousarray(pose32[:, 2]), True, silhouette, edge_scale,
                      g1, g2, pre, step, step, box32, K, T, coef, Z, points, valid)
        for k in range(3):
            observed_box[0, k] = box32[0, k]
    return win, depth, gray, pose32, (box32, K, gain, T, Z, coef, points, valid)


def bind_render_model(renderer: RasterRenderer, radius: float, *, margin_px: int = 24, canvas: int = 128,
                      box_margin_px: float = 20.0, edge_clip: float = 0.1,
                      silhouette: bool = True) -> "RenderModelBinding":
    """:func:`render_model_step` bound to a renderer and its options, unchecked, for a caller whose poses are valid
    (the tracker): a :class:`RenderModelBinding`."""
    return RenderModelBinding(renderer, radius, margin_px=margin_px, canvas=canvas, box_margin_px=box_margin_px,
                              edge_clip=edge_clip, silhouette=silhouette)


def _texture_args(texture):
    """The kernel's ``texture`` argument: a plain tuple of the texture's arrays, or ``None``."""
    return None if texture is None else tuple(texture)


class RenderModelBinding:
    """:func:`render_model_step` of one renderer and its options (:func:`bind_render_model`), callable as
    ``binding(pose, shaded, model) -> Rendered`` (``pose`` a ``(1, 7)`` float64 numpy array; ``model`` needs
    ``shaded``), and in three parts for a caller that runs the compiled call on another thread without the GIL in
    between: ``args = binding.start(pose, shaded, model)`` (the Python part before it), ``raw =
    binding.kernel(*args)`` (the compiled call: the only part that needs to run on the other thread) and
    ``binding.finish(raw)`` (the tensors of the result).

    Attributes:
        observed_box: ``(1, 3)`` float64, the canvas box of the last model made (its float32 box, as the
            observation of :mod:`~torchevtrack.stages.correction` takes it), written by the compiled call.
    """

    kernel = staticmethod(_render_model_kernel)  # the compiled call

    def __init__(self, renderer: RasterRenderer, radius: float, *, margin_px: int, canvas: int,
                 box_margin_px: float, edge_clip: float, silhouette: bool) -> None:
        mesh, cam = renderer.raster_mesh, renderer.camera
        self.observed_box = np.zeros((1, 3))
        step = max(1, canvas // 16)  # the model's object points: every step-th canvas pixel
        points = len(range(step // 2, canvas, step)) ** 2
        self._args = (np.full(1, float(radius)), np.array([cam.fx, cam.fy, cam.cx, cam.cy]), cam.width, cam.height,
                      float(margin_px), *mesh, renderer.znear, renderer.zfar, LIGHT_DIRECTION, AMBIENT,
                      renderer.background)
        self._model_args = (float(box_margin_px), silhouette, 0.125 / edge_clip, *_model_filters(canvas), canvas, step,
                            points, self.observed_box, _texture_args(renderer.raster_texture))

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
