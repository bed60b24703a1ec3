"""Step 5 of an update without the glue between its kernels: template model, observation, Newton search.

:func:`correction_step` runs, on numpy buffers and without per-stage checks, the kernels of three stage calls:
:func:`~torchevtrack.stages.template.template_model` of the render,
:func:`~torchevtrack.stages.eros.canvas_observation` of the EROS under the model's canvas box, and
:func:`~torchevtrack.stages.template.newton_search` from the predicted poses. Invariant: its results equal those of
the three stage calls exactly (``tests/test_correction.py``). The order: the canvas box from the render's extent, the observation under it, then the
rest of the template model and the search. Once the observation is made it tells (``on_observed``): from then on
the next window's events may update the surfaces while the model and the search run (the tracker's pipeline, see
:class:`~torchevtrack.tracker.EventPoseTracker`).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.stages.eros import _canvas_kernel, _check_time_surface, _decay_table
from torchevtrack.stages.template import (NEWTON_DAMPING, NEWTON_MAX_STEP, NUM_HYPOTHESES, Correction, TemplateModel,
                                          _camera_array, _model_in_box, _newton_kernel, _render_box, correct_canvas)

__all__ = ["CorrectionStep", "bind_correction", "correction_step"]


class CorrectionStep(NamedTuple):
    """Result of :func:`correction_step`: the template ``model`` of the render (or the one given) and the
    ``correction`` of the predicted poses, as :func:`~torchevtrack.stages.template.newton_search` returns it."""

    model: TemplateModel
    correction: Correction


def correction_step(
    render_pose: torch.Tensor,
    predicted: torch.Tensor,
    depth: torch.Tensor | None,
    gray: torch.Tensor | None,
    origin: torch.Tensor,
    surface: torch.Tensor,
    last_us: torch.Tensor,
    t_now_us: torch.Tensor,
    camera: Camera,
    *,
    model: TemplateModel | None = None,
    canvas: int = 128,
    margin_px: float = 20.0,
    edge_clip: float = 0.1,
    silhouette: bool = True,
    dp_px: float = 1.0,
    dtheta_deg: float = 0.5,
    rule: str = "newton",
    iterations: int = 1,
    max_age_us: int = 0,
    recency_us: float = 0.0,
    on_observed: Callable[[], object] | None = None,
) -> CorrectionStep:
    """Correct the ``predicted`` poses against the EROS with the template of a render (see the module docstring).

    Args:
        render_pose: ``(B, 7)`` float32 pose the render was made at; predicted: ``(B, 7)`` float64 start poses.
        depth, gray: ``(B, h, w)`` float32 render of the window at ``origin`` ``(B, 2)`` int64 (gray ``None``:
            silhouette only), or ``depth=None`` with a ``model`` of an earlier render to reuse.
        surface: ``(B, H, W)`` EROS; last_us: ``(B, C, H, W)`` int64 time surface; t_now_us: ``(B,)`` int64 us.
        camera: the frame camera.
        canvas, margin_px, edge_clip, silhouette: as for :func:`~torchevtrack.stages.template.template_model`.
        dp_px, dtheta_deg, rule, iterations: as for :func:`~torchevtrack.stages.template.correct_canvas` (the
            ``"newton"`` rule runs :func:`~torchevtrack.stages.template.newton_search`'s kernel directly).
        max_age_us, recency_us: as for :func:`~torchevtrack.stages.eros.canvas_observation`.
        on_observed: called (no arguments) once the observation is made: ``surface`` and ``last_us`` are not read
            after that.

    Shape: returns the model (``N = canvas``) and a ``Correction`` of ``B`` poses.
    """
    B = predicted.shape[0]
    if predicted.shape != (B, 7) or predicted.dtype != torch.float64:
        raise ValueError(f"predicted must be a float64 (B, 7) tensor, got {predicted.dtype} {tuple(predicted.shape)}")
    if surface.ndim != 3 or surface.shape[0] != B or t_now_us.shape != (B,):
        raise ValueError(f"surface (B, H, W) and t_now_us (B,) must have B = {B} rows, got {tuple(surface.shape)} "
                         f"and {tuple(t_now_us.shape)}")
    _check_time_surface(last_us, B, *surface.shape[1:])
    if model is None:
        _check_render(render_pose, depth, gray, origin, silhouette)
    elif model.coef.shape[0] != B:
        raise ValueError(f"model must have B = {B} elements, got {model.coef.shape[0]}")
    run = bind_correction(surface.numpy(), last_us.numpy(), camera, canvas=canvas, margin_px=margin_px,
                          edge_clip=edge_clip, silhouette=silhouette, dp_px=dp_px, dtheta_deg=dtheta_deg, rule=rule,
                          iterations=iterations, max_age_us=max_age_us, recency_us=recency_us)
    if model is None:
        step = run(render_pose.numpy(), predicted.numpy(), depth.numpy(), None if gray is None else gray.numpy(),
                   origin.numpy(), t_now_us.numpy(), on_observed=on_observed)
    else:
        step = run(None, predicted.numpy(), None, None, None, t_now_us.numpy(), model=model, on_observed=on_observed)
    return CorrectionStep(step.model, Correction(*(torch.from_numpy(a) for a in step.correction)))


def bind_correction(surface: np.ndarray, last_us: np.ndarray, camera: Camera, *, canvas: int = 128,
                    margin_px: float = 20.0, edge_clip: float = 0.1, silhouette: bool = True, dp_px: float = 1.0,
                    dtheta_deg: float = 0.5, rule: str = "newton", iterations: int = 1, max_age_us: int = 0,
                    recency_us: float = 0.0) -> Callable[..., CorrectionStep]:
    """:func:`correction_step` bound to the EROS ``surface`` ``(B, H, W)`` and time surface ``last_us`` (numpy views,
    read at each call) and its options, unchecked, for a caller that corrects every update (the tracker).

    Returns ``run(render_pose, predicted, depth, gray, origin, t_now_us, model=None, on_observed=None, obs=None)``,
    the arguments of :func:`correction_step` as numpy arrays (``render_pose`` float32; ``depth``, ``gray`` and
    ``origin`` ``None`` with a ``model`` to reuse), giving its :class:`CorrectionStep` with the fields of the
    correction as numpy arrays. ``obs``: the observation ``(B, N, N)`` under the ``model``'s box if it was made
    elsewhere (:func:`~torchevtrack.stages.eros.bind_observe`); the surfaces are then not read.
    """
    cam = _camera_array(camera)
    max_age_us, recency_us = int(max_age_us), float(recency_us)
    table = _decay_table(recency_us, max_age_us)
    dp, dtheta = float(dp_px), math.radians(dtheta_deg)

    def run(render_pose, predicted, depth, gray, origin, t_now_us, model=None, on_observed=None,
            obs=None) -> CorrectionStep:
        B = predicted.shape[0]
        if model is None:  # the canvas box first: the observation needs only that, the rest of the model can wait
            origin64 = origin.astype(np.float64)
            box, gain = _render_box(depth, origin64, cam, margin_px)
            N, observed_box = canvas, box.astype(np.float32).astype(np.float64)  # as the model's box (float32) gives it
        else:
            N = model.depth.shape[-1]
        if obs is None:
            obs = np.empty((B, N, N), dtype=np.float32)
            _canvas_kernel(surface, last_us, observed_box if model is None else _observed_box(model),
                           t_now_us.astype(np.int64, copy=False), max_age_us, recency_us, table, obs)
        if on_observed is not None:
            on_observed()
        if model is None:
            model = _model_in_box(render_pose.astype(np.float64), depth, depth if gray is None else gray,
                                  gray is not None, origin64, cam, box, gain, N, edge_clip, silhouette)
        if rule != "newton":
            c = correct_canvas(model, torch.from_numpy(predicted), torch.from_numpy(obs), camera, dp_px=dp_px,
                               dtheta_deg=dtheta_deg, rule=rule, iterations=iterations)
            return CorrectionStep(model, Correction(*(f.numpy() for f in c)))
        pose = np.empty((B, 7))
        score, scores, moved = np.empty(B), np.empty((B, NUM_HYPOTHESES)), np.empty(B, dtype=np.int64)
        _newton_kernel(model.coef.numpy(), model.depth.numpy(), model.K.numpy().astype(np.float64),
                       model.render_pose.numpy(), predicted, obs.reshape(B, N * N),
                       model.gain.numpy().astype(np.float64), camera.fx, camera.fy, dp, dtheta, iterations,
                       NEWTON_DAMPING, NEWTON_MAX_STEP, pose, score, scores, moved)
        dt = model.depth.numpy().dtype
        scores = scores.astype(dt)  # argmax: the first of ties, as torch's
        return CorrectionStep(model, Correction(pose, score.astype(dt), scores, scores.argmax(1),
                                                np.zeros((B, NUM_HYPOTHESES), dtype=np.bool_), moved))
    return run


def _check_render(render_pose, depth, gray, origin, silhouette) -> None:
    """The render of :func:`correction_step`: float32 ``(B, h, w)`` with its pose and window origin."""
    if depth is None or depth.ndim != 3 or depth.dtype != torch.float32 \
            or (gray is not None and gray.shape != depth.shape):
        raise ValueError("depth (and gray) must be float32 (B, h, w) renders, or pass the model to reuse")
    B = depth.shape[0]
    if render_pose.shape != (B, 7) or origin.shape != (B, 2):
        raise ValueError(f"render_pose (B, 7) and origin (B, 2) must have B = {B} rows, got "
                         f"{tuple(render_pose.shape)} and {tuple(origin.shape)}")
    if gray is None and not silhouette:
        raise ValueError("without a grey render the template needs silhouette=True")


def _observed_box(model: TemplateModel) -> np.ndarray:
    """The canvas box ``(B, 3)`` float64 a template model's observation is made under (its float32 box)."""
    return model.box.numpy().astype(np.float64)
