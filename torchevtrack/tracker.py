"""EventPoseTracker: the six stages composed into one batched tracker.

One update consumes the events of one window (``1 / rate_hz``, 2 ms by default) for each of ``B``
sequences and runs, in the paper's order:

1. :class:`~torchevtrack.stages.eros.EROS` and :class:`~torchevtrack.stages.flow.TripletFlow` take the events in
   one compiled call (:func:`~torchevtrack.update.bind_intake`). With the pipeline: for one stream with its
   template made ahead, the EROS (and a :class:`~torchevtrack.stages.eros.TimeSurface` of its own) on a thread of
   their own together with step 5's observation (:func:`~torchevtrack.stages.eros.bind_observe`) while the flow
   runs here; otherwise, when the window is known one update ahead, both on that thread during the previous update's
   step 5;
2. :class:`~torchevtrack.stages.velocity.VelocityKF` fuses the block flows, with depth sampled from the
   last render (the mesh at the previous pose: no depth sensor);
3. :func:`~torchevtrack.stages.propagate.propagate` moves the pose with the twist for one period (the
   filter's twist, plus with ``velocity.feedback_gain > 0`` the
   :class:`~torchevtrack.stages.velocity.CorrectionFeedback` on the axes the flow hardly observes: depth
   rate, pitch and yaw); steps 2 and 3 run as one compiled call of those stages' kernels,
   :func:`~torchevtrack.update.motion`;
4. the mesh is rendered once, in a window around the propagated pose; by default (``render.ahead``) around
   the pose the previous update predicted for this one (its propagated pose moved on by its twist), so that
   with the pipeline the render and its template model are made on the pipeline's thread during the previous
   update's step 5, in one compiled call (:class:`~torchevtrack.update.RenderModelBinding`);
5. :class:`~torchevtrack.stages.template.TemplateCorrector` scores hypotheses around the propagated pose,
   warped from that render, against the EROS observation (weighted toward its newest events: ``eros.recency_us``, a
   window that with ``eros.recency_px`` follows the speed of the last update's flow,
   :class:`~torchevtrack.stages.eros.Recency`) and moves the pose to the best (the paper's argmax of 13, or a Newton
   step over all six axes: ``template.rule``); the correction's rate feeds the feedback of step 3, if on;
6. with ``ukf.enabled`` (the paper's; off by default) :class:`~torchevtrack.stages.ukf.PoseUKF` smooths the
   corrected pose into the output, else the corrected pose is the output (with the correction feedback's update and
   the output checks, one compiled call: :func:`~torchevtrack.update.output`);
0. before all of them, the :class:`~torchevtrack.stages.burst.BurstGuard` (``config.burst``, on by default) counts
   each element's events in the window; a burst's (a flash, a camera bump) are dropped before any stage sees them,
   so that update costs what an empty window does: the velocity filter predicts without a measurement, the template
   corrects against the EROS as it was, and the loss detector takes the update as neutral (``Quality.burst``);
   then, optionally (``config.denoise.enabled``), the
   :class:`~torchevtrack.stages.denoise.BackgroundActivityFilter` drops the kept events no neighbour supports;
7. optionally (``config.loss.enabled``) a :class:`~torchevtrack.loss.LossDetector` judges the update's
   :class:`Quality` and declares elements lost; an ``on_lost`` callback may give them new poses, and
   those elements (only) restart there;
8. optionally (``config.recover.enabled``) the :class:`~torchevtrack.recover.Recoverer` searches for a lost
   element (:class:`~torchevtrack.stages.relocalise.Relocaliser`) and restarts it where the search finds the object
   clearly and better than the tracker's own pose, or clears its flag where the search confirms that pose.

The render of step 4 also provides the depth for step 2 of the next update, so an update costs one
render. Ablations of the paper are configuration switches (:data:`torchevtrack.config.ABLATIONS`).

Example:
    >>> import torch
    >>> from torchevtrack import Camera, EventPoseTracker
    >>> cam = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
    >>> tracker = EventPoseTracker(cam, "can")
    >>> tracker.reset(torch.tensor([0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0]))
    >>> e = torch.zeros(0, dtype=torch.long)
    >>> tracker(e, e, e, e).shape  # an empty window keeps the pose
    torch.Size([1, 7])
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence, TypeVar

import numpy as np
import torch
import trimesh
from torch import nn
from tqdm.auto import tqdm

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream, check_window, first_invalid, pack_streams
from torchevtrack.geometry import check_pose, quat_rotate
from torchevtrack.hypotheses import Hypotheses
from torchevtrack.loss import LossDetector, LossUpdate, OnLost, update_times
from torchevtrack.kernels import compile_cold
from torchevtrack.mesh import hidden_symmetry_axis, load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.recover import Recoverer
from torchevtrack.render import make_renderer
from torchevtrack.schedule import Job, Schedule
from torchevtrack.stages import batch_mask, periods
from torchevtrack.stages.burst import BurstGuard, keep_events
from torchevtrack.stages.denoise import BackgroundActivityFilter
from torchevtrack.stages.eros import EROS, Recency, TimeSurface, bind_observe, canvas_observation
from torchevtrack.stages.flow import FlowField, TripletFlow
from torchevtrack.stages.propagate import invalid_poses, propagate
from torchevtrack.stages.template import Correction, TemplateCorrector, TemplateModel, area_weight, window_of
from torchevtrack.stages.ukf import PoseUKF
from torchevtrack.stages.velocity import CorrectionFeedback, VelocityKF, shift_twist
from torchevtrack.update import (CorrectionStep, MotionArgs, OutputArgs, RenderModelBinding, bind_correction,
                                 bind_intake, motion, output, render_ahead, watch)

if TYPE_CHECKING:
    from torchevtrack.render import Renderer

__all__ = ["EventPoseTracker", "Quality"]

MeshLike = str | Path | trimesh.Trimesh


@dataclass
class Quality:
    """Per-update diagnostics, one value per batch element.

    Attributes:
        score: ``(B,)`` template score of the corrected pose (NaN when correction is off).
        flow_vectors: ``(B,)`` flow vectors the velocity filter used.
        events: ``(B,)`` events in the window.
        rejected: ``(B,)`` bool, the update produced an invalid pose (non-finite, or the object at or
            behind the camera) and the previous pose was kept.
        burst: ``(B,)`` bool, the burst guard dropped the window's events (``events`` still counts them); ``None``:
            no guard.
    """

    score: torch.Tensor
    flow_vectors: torch.Tensor
    events: torch.Tensor
    rejected: torch.Tensor
    burst: torch.Tensor | None = None


class _StageClock:
    """Wall-clock milliseconds of consecutive pipeline stages (``ms[name]``)."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.ms[name] = (now - self._t) * 1e3
        self._t = now


class EventPoseTracker(nn.Module):
    """Track ``B`` objects (or sequences) from events.

    Args:
        camera: the event camera (all batch elements share it).
        meshes: one mesh for all, or a list of ``B`` meshes: paths, built-in / YCB names or trimesh objects.
        config: :class:`~torchevtrack.config.TrackerConfig` (default: the paper's settings).
        batch_size: ``B`` when one mesh is given for several sequences (default 1).
        workers: threads that run the batch's EROS, flow, renders and template corrections, each on its own share
            of the elements (the compiled kernels release the GIL, so they run on as many cores); default
            ``min(B, usable cores)``, 1 runs everything in the calling thread. Results do not depend on it.
        pipeline: with one worker, let a thread of its own share each update. With ``render.ahead`` (default),
            one sequence, the compiled rasteriser and the template on, that thread makes the next update's render
            and template model (:class:`~torchevtrack.update.RenderModelBinding`) while an update
            searches, and takes each window into the EROS and the time surface and observes it
            (:func:`~torchevtrack.stages.eros.bind_observe`) while the calling thread runs the flow. Otherwise it
            takes the next window's events into the EROS and the flow
            (:func:`~torchevtrack.update.bind_intake`) while an update searches, whenever that window is
            known: in :meth:`track`, and in :class:`~torchevtrack.online.OnlineTracker` when a push completes
            several windows (and with ``render.ahead``, one sequence, also makes the next update's render); not with
            a twin (``config.hypotheses``), nor in an update in which the re-localiser may search
            (:meth:`~torchevtrack.recover.Recoverer.may_search`): both read the surfaces after the update. Default:
            on with one worker and two or more usable cores. Results do not depend on it; with it, the ``eros``,
            ``flow``, ``render`` and ``correction`` of ``stage_ms`` include the waits for that thread.
        on_lost: re-initialisation callback of the loss detector (needs ``config.loss.enabled``):
            ``on_lost(batch_indices (K,) int64, t_us (K,) int64) -> poses (K, 7) or None``, called with
            the elements declared lost in an update; the elements it returns poses for restart there
            (:meth:`reset` with a mask) before the update returns, so its output holds those poses.

    Buffers:
        pose: ``(B, 7)`` float64 current output pose (also while :attr:`lost`: the tracker's own estimate; with
            ``config.recover``, ``recover.good_pose`` holds each element's last good pose). With
            ``config.hypotheses``, this tracker's own hypothesis: the output (:meth:`forward`'s, :meth:`track`'s) is
            the chosen one's, ``hypotheses.output(tracker, tracker.twin)`` (:mod:`torchevtrack.hypotheses`).
        prev_pose: ``(B, 7)`` float64 output pose of the previous update.
        depth_lag: ``(B,)`` float64 metres, the last update's measured (corrected) depth less its output depth (0
            without the UKF). The next correction's depth stays within ``template.max_depth_speed`` times the period
            of the predicted depth plus this lag: the last measurement moved on by the prediction.
        depth: ``(B, h, w)`` float32 depth of the last render window; ``origin``: ``(B, 2)`` its top-left pixel.

    After each update, ``quality`` holds its :class:`Quality` and ``stage_ms`` the milliseconds spent in
    each stage (eros, flow, velocity, render, correction, ukf; and loss with a detector; ukf includes the
    correction feedback's update, which runs with it; the EROS and the flow, and the time surface where one is kept,
    run as one compiled call per worker, :func:`~torchevtrack.update.bind_intake`, whose time counts as the
    flow's). With
    ``config.loss.enabled``, ``loss`` is the :class:`~torchevtrack.loss.LossDetector` (its buffers:
    confidence, lost, lost_at_us, ...), ``loss_update`` the :class:`~torchevtrack.loss.LossUpdate` of
    the last update and ``lost`` its ``(B,)`` flags; without it all three are ``None``.

    Batch elements do not share state, and each is rendered in a window that depends on its own pose
    only: :meth:`reset` with a mask restarts some elements, and the others' poses continue as if nothing
    had happened: exactly with one argmax correction round per update and no correction feedback;
    otherwise the float32 rounding of the correction differs with the other elements' data (about 1e-8 m)
    and carries on into the poses.
    """

    def __init__(
        self,
        camera: Camera,
        meshes: MeshLike | Sequence[MeshLike],
        config: TrackerConfig | None = None,
        batch_size: int | None = None,
        on_lost: OnLost | None = None,
        workers: int | None = None,
        pipeline: bool | None = None,
    ) -> None:
        super().__init__()
        cfg = config or TrackerConfig()
        if isinstance(meshes, (str, Path, trimesh.Trimesh)):
            meshes = [meshes] * (batch_size or 1)
        elif not isinstance(meshes, (list, tuple)) or not all(isinstance(m, (str, Path, trimesh.Trimesh)) for m in meshes):
            raise TypeError("meshes must be a mesh (path, object name or trimesh.Trimesh) or a list of them, "
                            f"got {type(meshes).__name__}")
        elif batch_size is not None and batch_size != len(meshes):
            raise ValueError(f"batch_size={batch_size} but {len(meshes)} meshes were given")
        if not meshes:
            raise ValueError("at least one mesh is needed")
        B = len(meshes)
        self.camera, self.config, self.batch_size = camera, cfg, B
        self._schedule = Schedule(B, workers, pipeline)
        self.period_us = cfg.period_us
        self.dt = self.period_us * 1e-6

        # One renderer per distinct mesh (sequences of the same object share it).
        self._renderers: list[Renderer | RasterRenderer] = []
        self._renderer_of: list[int] = []
        self._radius: list[float] = []
        self._sym_axes: list[torch.Tensor] = []
        distinct: list[trimesh.Trimesh] = []
        seen: dict[int, int] = {}
        for m in meshes:
            key = id(m) if isinstance(m, trimesh.Trimesh) else hash(str(m))
            if key not in seen:
                mesh = load_mesh(m, decimate=cfg.render.decimate) if cfg.render.decimate else load_mesh(m)
                seen[key] = len(self._renderers)
                distinct.append(mesh)
                self._renderers.append(make_renderer(mesh, camera, cfg.render.backend))
                self._radius.append(float(torch.as_tensor(mesh.vertices).norm(dim=1).max()))
                axis = hidden_symmetry_axis(mesh) if self._feedback_on(cfg) else None
                self._sym_axes.append(torch.zeros(3, dtype=torch.float64) if axis is None else torch.as_tensor(axis))
            self._renderer_of.append(seen[key])
        # OpenGL contexts belong to the thread that made them: only the compiled rasteriser renders in the workers.
        self._threaded_render = self._schedule.pooled and cfg.render.backend == "raster"

        H, W = camera.height, camera.width
        self.eros = EROS.from_config(H, W, cfg.eros, batch_size=B)
        self.recency = Recency.from_config(cfg.eros, batch_size=B)
        self.flow = TripletFlow.from_config(H, W, cfg.flow, batch_size=B)
        v, t = cfg.velocity, cfg.template
        self.velocity = VelocityKF.from_config(camera, v, normal=cfg.flow.estimate == "normal", batch_size=B)
        # Feedback of the corrections into the flow twist (needs both; off in the paper's ablations without them).
        self.feedback = CorrectionFeedback.from_config(v, batch_size=B) if self._feedback_on(cfg) else None
        self.corrector = TemplateCorrector.from_config(camera, t)
        o = self.corrector.options
        # each compiled rasteriser's render (and template model) of a pose in its window, in one compiled call
        self._render_bindings = [
            RenderModelBinding(r, radius, margin_px=cfg.render.margin_px, canvas=o["canvas"],
                               box_margin_px=o["margin_px"], edge_clip=o["edge_clip"], silhouette=o["silhouette"],
                               interior=o["interior"])
            if isinstance(r, RasterRenderer) else None for r, radius in zip(self._renderers, self._radius)]
        self._render_one = self._render_bindings[0] if B == 1 else None  # one stream: the render is the buffer
        # The pipeline's thread takes a known next window in ahead, unless it makes each update's render and template
        # ahead (one stream, compiled rasteriser): it then takes each window into the EROS side and observes it while
        # the flow runs here, which splits an update more evenly between the two threads (both give the same poses). That
        # observation weighs the EROS by a time surface of the EROS side's own (the flow writes its SAE meanwhile);
        # otherwise the observation reads the SAE's channel maximum, the same numbers, and no time surface is kept
        # (for a batch, ~20 MB less memory traffic per step).
        observes = self._schedule.pipelined and self._render_one is not None and cfg.render.ahead and t.enabled
        # (not with a twin: it reads these surfaces after this tracker's update, so the next window must wait)
        self._take_in_ahead = self._schedule.pipelined and not observes and not cfg.hypotheses.enabled
        self.time_surface = TimeSurface(H, W, batch_size=B) if observes else None
        self.ukf = PoseUKF.from_config(cfg.ukf, batch_size=B)
        bc = cfg.burst
        self.burst = BurstGuard(H, W, min_fraction=bc.min_fraction, ratio=bc.ratio, ema=bc.ema, max_run=bc.max_run,
                                batch_size=B) if bc.enabled else None
        dc = cfg.denoise
        self.denoise = BackgroundActivityFilter(H, W, dt_us=dc.dt_us, hot_period_us=dc.hot_period_us,
                                                hot_ratio=dc.hot_ratio, hot_min_rate_hz=dc.hot_min_rate_hz,
                                                batch_size=B) if dc.enabled else None
        lc = cfg.loss
        if lc.enabled:
            # Without flow velocity no flow vectors are counted: the flow criterion would flag every update.
            self.loss = LossDetector(B, score_threshold=lc.score_threshold,
                                     min_flow_vectors=lc.min_flow_vectors if v.source == "flow" else 0,
                                     patience=lc.patience, recovery=lc.recovery, ema=lc.ema, on_lost=on_lost)
        elif on_lost is not None:
            raise ValueError("on_lost needs the loss detector: set loss.enabled in the config")
        else:
            self.loss = None
        self.recover = Recoverer.from_config(cfg.recover, camera, distinct, self._renderer_of, self._radius) \
            if cfg.recover.enabled else None
        if cfg.hypotheses.enabled:  # the twin: this tracker without the UKF (and without loss, recovery or a twin)
            off, no_recover = {"enabled": False}, {"enabled": False, "start_search": False}
            self.twin = EventPoseTracker(camera, [distinct[i] for i in self._renderer_of],
                                         cfg.replace(ukf=off, loss=off, recover=no_recover, hypotheses=off,
                                                     render={"decimate": None}),
                                         workers=workers, pipeline=pipeline)
            self.twin._follow(self)
            self.hypotheses = Hypotheses.from_config(cfg.hypotheses, camera, distinct, self._renderer_of,
                                                     self._radius)
        else:
            self.twin, self.hypotheses = None, None

        f64 = torch.float64
        self.register_buffer("pose", torch.zeros(B, 7, dtype=f64))
        self.register_buffer("prev_pose", torch.zeros(B, 7, dtype=f64))
        self.register_buffer("depth_lag", torch.zeros(B, dtype=f64))
        self.register_buffer("depth", torch.zeros(B, 1, 1))
        self.register_buffer("origin", torch.zeros(B, 2, dtype=torch.long))
        self.register_buffer("events_seen", torch.zeros(B, dtype=torch.long))
        self.register_buffer("t_last", torch.zeros(B, dtype=torch.long))
        self._run = _UpdateState(Quality(torch.full((B,), float("nan")), torch.zeros(B, dtype=torch.long),
                                         torch.zeros(B, dtype=torch.long), torch.zeros(B, dtype=torch.bool),
                                         None if self.burst is None else torch.zeros(B, dtype=torch.bool)))
        self.stage_ms: dict[str, float] = {}
        # The object centre must stay farther than its bounding radius (plus the near plane).
        self.register_buffer("_symmetry_axis", torch.stack([self._sym_axes[i] for i in self._renderer_of]),
                             persistent=False)  # (B, 3) object frame, zero: none
        self._symmetric = bool(self._symmetry_axis.any())
        self._radius_of = torch.tensor([self._radius[i] for i in self._renderer_of], dtype=torch.float64)  # (B,)
        self.register_buffer("_min_depth", self._radius_of + 0.01, persistent=False)
        # render.ahead: where the next update renders (the last prediction moved on by its twist), when valid
        self.register_buffer("_render_next", torch.zeros(B, 7, dtype=f64))
        self.register_buffer("_render_next_ok", torch.zeros(B, dtype=torch.bool))
        compile_cold(progress=True)  # a cold cache: one line on stderr, the kernels compiled in worker processes

    def _set_depth(self, depth: torch.Tensor) -> None:
        """Replace the depth buffer (the registered name, without nn.Module's checks: ``depth`` is a tensor)."""
        self._buffers["depth"] = depth

    # -- state -------------------------------------------------------------------------------
    @torch.inference_mode()
    def reset(self, initial_pose: torch.Tensor, twist: torch.Tensor | None = None,
              mask: torch.Tensor | None = None) -> None:
        """Restart every element at ``initial_pose`` ``(B, 7)`` or ``(7,)`` (validated), optional twist ``(B, 6)``.

        ``mask`` (``(B,)`` bool or ``(K,)`` indices) restarts only the selected elements, e.g. to
        re-initialise lost ones mid-stream: their EROS and time surface are cleared, their velocity
        filter, UKF, pose, events seen and loss-detector state start over as in a full reset, and their
        depth is rendered at the new pose. The other elements keep their state exactly (the depth
        buffer may grow to a larger common window, which zero-pads theirs: exact, their objects lie
        inside their old windows), and their rows of ``initial_pose`` and ``twist`` are ignored.
        """
        B = self.batch_size
        m = batch_mask(mask, B)
        pose = torch.as_tensor(initial_pose, dtype=torch.float64)
        if pose.shape[-1:] != (7,):
            raise ValueError(f"initial_pose must have shape (..., 7) [tx, ty, tz, qw, qx, qy, qz], "
                             f"got {tuple(pose.shape)}")
        pose = pose.expand(B, 7).clone() if pose.ndim == 1 else pose.clone()
        if pose.shape != (B, 7):
            raise ValueError(f"initial_pose must have shape ({B}, 7) or (7,), got {tuple(pose.shape)}")
        if twist is None:
            twist = torch.zeros(B, 6, dtype=torch.float64)
        elif not isinstance(twist, torch.Tensor) or twist.shape != (B, 6):
            raise TypeError(f"twist must be a ({B}, 6) tensor [v, w], got "
                            f"{tuple(twist.shape) if isinstance(twist, torch.Tensor) else type(twist).__name__}")
        elif not bool(torch.isfinite(twist[m]).all()):
            raise ValueError("twist contains NaN or infinite values")
        # Unselected rows are ignored: they take the current pose and zero motion (valid values throughout).
        pose = torch.where(m[:, None], pose, self.pose)
        pose[m] = check_pose(pose[m], "initial_pose")
        twist = torch.where(m[:, None], twist.double(), 0.0)
        if bool((invalid_poses(pose, self._min_depth) & m).any()):
            raise ValueError("initial_pose puts the object centre closer to the camera than the object's radius")
        self._drop_render()
        self._render_next_ok.masked_fill_(m, False)
        if self._run.ahead is not None:  # the intake thread is done with the surfaces before they are cleared
            self._run.ahead.flow.result()
            if mask is None:  # a fresh start: that window is not coming
                self._run.ahead = None
        if mask is None:
            self._run.guarded = None
        if self.burst is not None:
            self.burst.reset(m)
        if self.denoise is not None:
            self.denoise.reset(m)
        self.eros.reset(m)
        self.recency.reset(m)
        if self.time_surface is not None:
            self.time_surface.reset(m)
        self.flow.reset(m)
        if self._run.ahead is not None:
            self._retake_ahead(m)
        self.velocity.reset(shift_twist(twist, pose[:, :3]), m)  # about the centre
        self.ukf.reset(pose, twist, m)
        self.pose.copy_(pose)
        self.prev_pose.copy_(torch.where(m[:, None], propagate(pose, twist, -self.dt), self.prev_pose))
        self.depth_lag.masked_fill_(m, 0.0)
        self.events_seen.masked_fill_(m, 0)
        if self.feedback is not None:
            self.feedback.reset(m)
        self.t_last.masked_fill_(m, 0)
        if self.loss is not None:
            self.loss.reset(m)
        if self.recover is not None:
            self.recover.reset(pose, m)
        if self.twin is not None:
            self.twin.reset(pose, twist, m)
            self.hypotheses.reset(m)
        if mask is None:
            self._run.loss_report = None
            self._render(pose.numpy(), shaded=False)
        else:
            self._render_depth(pose, m)
        self._run.models = None  # the template of the last render

    def close(self) -> None:
        """Release the renderers' GL contexts and the worker threads."""
        for r in self._renderers:
            r.close()
        if self.recover is not None:
            self.recover.close()
        if self.twin is not None:
            self.twin.close()
            self.hypotheses.close()
        self._schedule.close()

    # -- one update --------------------------------------------------------------------------
    def forward(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor,
                b: torch.Tensor | None = None, t_us: int | torch.Tensor | None = None, *,
                next_window: tuple | None = None, check: bool = True) -> torch.Tensor:
        """Consume one window of packed events and return the new poses ``(B, 7)`` float64.

        Args:
            x, y: ``(N,)`` integer pixels inside the camera; t: ``(N,)`` integer microseconds, ``>= 0``; p: ``(N,)``
                polarity {0, 1}; b: ``(N,)`` batch index in ``[0, B)`` (None: all batch element 0). Time order within
                each batch element, and no event of an element before the latest of its previous windows.
            t_us: time stamp of this update (int or ``(B,)`` int64 us, the window end), given to the loss
                detector and ``on_lost``; default: the latest event time seen per element.
            next_window: the next window's ``(x, y, t, p, b)``, if it is already known. When the pipeline takes
                windows in ahead (see ``pipeline``), its events go into the EROS and the flow while
                this update searches (until the next call, those stages' state belongs to the intake thread), and
                the next call must be for exactly these tensors (else RuntimeError); otherwise it is ignored. Only
                a window already in the kernels' dtypes (an :class:`EventStream`'s: int16 x and y, int64 t, int8
                p, int64 b) that passes the checks is taken in ahead. A loop that passes it ends with
                :meth:`drop_ahead`.
            check: validate the window (:func:`~torchevtrack.events.check_window`, and time going back across
                windows), raising a one-line ``ValueError`` that names the tensor and the event, and cast it once
                to the kernels' dtypes (other integer dtypes would compile every kernel again). ``False`` skips
                both, for windows known to be valid and in those dtypes (:meth:`track` checks its streams once).

        Raises:
            RuntimeError: before the first :meth:`reset`.

        The update runs in ``torch.inference_mode`` (no autograd bookkeeping on its many small tensor
        operations); the returned poses are ordinary tensors.
        """
        last = self.t_last.numpy()
        if not self.pose.numpy()[:, 3:].any(axis=1).all():  # reset gives every element a unit quaternion
            raise RuntimeError("the tracker has no pose yet: call reset(pose) before the first update")
        ahead_of = None if self._run.ahead is None else self._run.ahead.window[0]
        if check and x is not ahead_of:  # (a window taken in ahead was checked before it went in)
            x, y, t, p, b = self._check(x, y, t, p, b, last)
        if check and next_window is not None and self._take_in_ahead:
            latest = last.copy()
            if t.numel() and b is None:
                latest[0] = max(latest[0], t.numpy().max())
            elif t.numel():
                np.maximum.at(latest, b.numpy(), t.numpy())
            try:
                if any(c is not g for c, g in zip(self._check(*next_window, latest), next_window)):
                    next_window = None  # other dtypes: checked and cast when its own update comes
            except ValueError:
                next_window = None  # its own update raises
        ahead = next_window if self._take_in_ahead else None
        if ahead is not None and self.recover is not None and self.recover.may_search():
            ahead = None  # a search reads the time surface of this window's events: the next must not be going in
        with torch.inference_mode():
            try:
                intake = self._update(x, y, t, p, b, t_us, ahead)
            finally:
                if self._run.observing is not None:  # the update failed after it gave the intake thread its part
                    self._run.observing.wait()
                    self._run.observing = None
            if self.twin is not None:
                self.twin._update(*intake.window, t_us, None, intake)
        if self.twin is None:  # (made outside inference mode: an ordinary tensor)
            return torch.from_numpy(self.pose.numpy().copy())
        self.hypotheses(self, self.twin, self.t_last if t_us is None else t_us)
        return self.hypotheses.output(self, self.twin)

    def drop_ahead(self) -> None:
        """Forget a window given as ``next_window`` to :meth:`forward` whose update will not come: a caller that feeds
        windows ahead calls it when its loop ends (in a ``finally``; nothing happens if no window is ahead). It waits
        for the pipeline's thread to finish taking that window in; the state then holds its events (the next update
        must not be for them). A render made ahead stays: it depends on the poses only."""
        if self._run.ahead is not None:
            self._run.ahead.flow.wait()  # not .result(): in a finally, its error would hide the one that stopped the loop
            self._run.ahead = None

    def _check(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor, b: torch.Tensor | None,
               last: np.ndarray) -> tuple[torch.Tensor, ...]:
        """A window checked and in the kernels' dtypes (:func:`~torchevtrack.events.check_window`), none of whose
        events comes before ``last`` ``(B,)``, its element's latest event time so far. A window of one element already
        in those dtypes (an :class:`EventStream`'s) takes one compiled pass and one numpy pass (a few microseconds for
        thousands of events); any other goes through :func:`~torchevtrack.events.check_window`, which also finds the
        message."""
        W, H = self.camera.width, self.camera.height
        fast = b is None and all(isinstance(v, torch.Tensor) and v.ndim == 1 and v.is_contiguous()
                                 for v in (x, y, t, p)) \
            and x.dtype == y.dtype == torch.int16 and t.dtype == torch.int64 and p.dtype == torch.int8 \
            and x.shape == y.shape == t.shape == p.shape
        if fast and t.numel():
            fast = first_invalid(x.numpy(), y.numpy(), t.numpy(), W, H)[0] == 0 and \
                int(p.numpy().view(np.uint8).max()) <= 1
        if not fast:
            x, y, t, p, b = check_window(x, y, t, p, b, width=W, height=H, batch=self.batch_size)
        if t.numel():
            tn = t.numpy()
            back = tn[:1] < last[0] if b is None else tn < last[b.numpy()]  # (one element: sorted, its first)
            if back.any():
                i = int(back.argmax())
                k = 0 if b is None else int(b[i])
                where = "" if b is None else f" of batch element {k}"
                raise ValueError(f"t goes back in time across windows at event {i}{where}: {int(tn[i])} us after "
                                 f"{int(last[k])} us in an earlier window")
        return x, y, t, p, b

    def _intake(self, window: tuple, ahead: tuple | None, run: "_Bound", clock: "_StageClock") -> "_Intake":
        """Step 1 of an update: the burst guard and the denoise filter on the packed ``window`` ``(x, y, t, p, b)``,
        then its kept events into the EROS, the time surface and the flow (or their flow, taken in ahead); ``ahead``:
        the next window, to take in once this update has read the surfaces (``launch``)."""
        (x, y, t, p, b), counts, seen, burst = self._guard(window)
        if ahead is not None:  # judged now, in window order, so that only its kept events go in ahead
            ahead = self._guard_ahead(ahead)
        launch = None if ahead is None else lambda: self._launch(ahead)  # once this update has read the surfaces
        if self._run.ahead is not None:  # this window went in on the intake thread during the last update
            clock.lap("eros")
            flow = self._take_ahead(x)
        elif self._run.rendering is not None and self.time_surface is not None:
            # the render and template made ahead: the EROS, the time surface and the observation on the pipeline's
            # thread, after that render, while this one runs the flow
            clock.lap("eros")
            flow = run.intake[0](x, y, t, p, b, surfaces=False,
                                 checked=lambda *ev: self._observe_soon(*ev, self._t_now(t, b).copy()))
        elif not self._schedule.pooled:  # the three stages in one compiled call: its time counts as the flow's
            clock.lap("eros")
            flow = run.intake[0](x, y, t, p, b)
        else:  # each worker takes the events of its share of the batch
            events = self._schedule.split(x, y, t, p, b)
            clock.lap("eros")
            flow = _cat(self._schedule.map(lambda rows, intake, ev: intake(*ev), run.intake, events))
        if burst is not None and burst.any():  # no flow measurement from a burst: the velocity filter predicts
            flow.valid[burst] = False  # (the bound intake gives numpy arrays)
        clock.lap("flow")
        return _Intake((x, y, t, p, b), flow, counts, seen, burst, launch)

    def _update(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor, b: torch.Tensor | None,
                t_us: int | torch.Tensor | None, ahead: tuple | None, intake: "_Intake | None" = None) -> "_Intake":
        """One update (:meth:`forward`): the new poses go to :attr:`pose`. ``intake``: the window already taken into
        this tracker's event stages by the tracker it follows (:meth:`_follow`), whose update returned it; returns
        this window's :class:`_Intake`."""
        cfg = self.config
        B = self.batch_size
        run = self._run.bound or self._bind()
        clock = _StageClock()
        if intake is None:
            intake = self._intake((x, y, t, p, b), ahead, run, clock)
        else:
            clock.lap("eros")
            clock.lap("flow")
        (x, y, t, p, b), flow, counts, seen, burst, launch = intake

        # A pose that is not finite or puts the object (nearly) behind the camera is not a pose: such a
        # prediction or output is replaced by the last pose (zero motion) rather than used or emitted.
        predicted, twist, n_vectors, rejected = motion(run.motion, flow, self.depth.numpy(), run.origin)
        if launch is not None and not cfg.template.enabled:  # nothing reads the surfaces after the flow
            launch()
        clock.lap("velocity")

        render_pose, pose32 = self._render_pose_ahead(predicted, twist) if cfg.render.ahead else \
            (predicted, predicted.astype(np.float32))
        render = self._render(render_pose, shaded=cfg.template.enabled)
        if render.models is not None:  # None: the correction uses self._run.models, the template made with this render
            self._run.models, render = render.models, None
        if self._schedule.pipelined and cfg.render.ahead and run.render_next_ok.all():
            # the template model too, unless the thread will take the next window in (it would then wait)
            self._render_soon(run.render_next.copy(), cfg.template.enabled,
                              model=cfg.template.enabled and ahead is None)
        clock.lap("render")
        n_events = counts
        run.events_seen[:] += seen
        if cfg.template.enabled:
            if self._run.observing is not None:  # (its window's times went into t_last when it was given out)
                observing, self._run.observing = self._run.observing, None
                obs, t_now = observing.result(), run.t_last  # obs None (no box): the correction observes itself
            else:
                obs, t_now = None, self._t_now(t, b)
            z_ref = predicted[:, 2] + run.output.depth_lag  # the last measurement moved on by the prediction
            corr = self._correct(predicted, z_ref, pose32, render, t_now, launch, obs)
            # Until the EROS holds enough events, its edges are too sparse to correct against.
            warm = (run.events_seen >= cfg.template.warmup_events)[:, None]
            measured = np.where(warm, corr.pose, predicted)
            score = corr.score
        else:
            measured, score = predicted, np.full(B, np.nan, dtype=np.float32)
        clock.lap("correction")

        # the objects' symmetry axes in the camera frame, for the feedback (zero stays zero; none: no rotation)
        axis = quat_rotate(torch.from_numpy(measured[:, 3:]), self._symmetry_axis).numpy() \
            if self.feedback is not None and self._symmetric else None
        out, bad = output(run.output, predicted, measured, twist, axis)
        run.recency(flow.flow, flow.valid)  # the next observations' windows
        clock.lap("ukf")
        run.prev_pose[:] = run.pose
        run.pose[:] = out
        rejected = bad | rejected
        self._run.quality = (score, n_vectors, n_events, rejected) + (() if burst is None else (burst,))
        if self.loss is not None:  # the loss rule and the re-localiser's books; the report is made when read
            t_now = run.t_last.copy() if t_us is None else update_times(t_us, B)  # a copy: a restart resets t_last
            newly, search = watch(self.loss.arrays(), None if self.recover is None else self.recover.arrays(), score,
                                  n_vectors, rejected, burst, t_now, self.period_us, run.pose)
            self._run.loss_report = True
            if newly and self.loss.on_lost is not None:
                upd = self._run.loss_report = self.loss.report(t_now)
                if upd.reinit_index.numel():  # on_lost gave poses: those elements restart there (the detector did)
                    pose = self.pose.clone()
                    pose[upd.reinit_index] = upd.reinit_pose
                    lost_at = self.loss.lost_at_us.clone()
                    self.reset(pose, mask=upd.reinit_index)
                    self.loss.lost_at_us.copy_(lost_at)  # the first loss stays on record
            clock.lap("loss")
            if search:  # may restart elements (a masked reset)
                self.recover.search(self, t_now)
            clock.lap("recover")
        self.stage_ms = clock.ms
        return intake

    @property
    def quality(self) -> Quality:
        """The last update's :class:`Quality` (made from its numpy fields when first asked for)."""
        if not isinstance(self._run.quality, Quality):
            self._run.quality = Quality(*(torch.from_numpy(np.asarray(f)) for f in self._run.quality))
        return self._run.quality

    @property
    def pipelined(self) -> bool:
        """A thread of its own shares each update (the ``pipeline`` argument, its default resolved)."""
        return self._schedule.pipelined

    @property
    def loss_update(self) -> LossUpdate | None:
        """The loss detector's :class:`~torchevtrack.loss.LossUpdate` of the last update (made when first read after
        it); ``None`` without a detector or before the first update."""
        report = self._run.loss_report
        if report is True:
            report = self._run.loss_report = self.loss.report(np.zeros(self.batch_size, np.int64))  # (no callback)
        return report

    @property
    def lost(self) -> torch.Tensor | None:
        """``(B,)`` bool: the loss detector held the element lost after the last update (before any
        re-initialisation in that update); with ``config.recover``, the :class:`~torchevtrack.recover.Recoverer`'s
        flags (lost until a search restarts the element or confirms its pose, or drifted in depth by its last depth
        check); ``None`` without a detector or before the first update."""
        if self._run.loss_report is None:
            return None
        return self.loss_update.lost if self.recover is None else self.recover.lost | self.recover.drifted

    @property
    def last_event_us(self) -> torch.Tensor:
        """The newest event time per pixel, int64 microseconds: ``(B, H, W)`` (the ``time_surface`` stage, where the
        tracker keeps one) or ``(B, C, H, W)`` per polarity channel (the flow's ``newest``);
        :data:`~torchevtrack.stages.NEVER` where none fired. The tracker's own buffer: clone it to keep it."""
        return self.time_surface.last_us if self.time_surface is not None else self.flow.newest

    def _observed_us(self) -> torch.Tensor:
        """:attr:`last_event_us` as the observation reads it: ``(B, C, H, W)`` (one channel for the time surface)."""
        last = self.last_event_us
        return last[:, None] if last.ndim == 3 else last

    @torch.inference_mode()
    def refine(self, poses: torch.Tensor, index: int, t_us: int, rounds: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
        """Candidate poses of element ``index`` refined by the template correction against its current observation.

        Each pose gets ``rounds`` corrections (a render in the update's window around the pose, its template model,
        the update's Newton search against the EROS observation in that model's canvas at time ``t_us``, the
        element's recency window), then a last render scores it as the correction does (edges and interior, less the
        area term). Slow path (a render per round, Python glue; 13 poses at two rounds: about 0.05 s at 640x480,
        0.11 s at 1280x720): for searches, not for updates. The element's state is not changed.

        Args:
            poses: ``(K, 7)`` float64 poses of the element's object.
            index: the element; t_us: the observation's time (int microseconds, the element's last update).
            rounds: corrections before the score (``>= 0``).

        Returns:
            ``(K, 7)`` float64 refined poses and ``(K,)`` float64 scores (``-inf`` where the object is out of view).

        Example:
            >>> import torch
            >>> from torchevtrack import Camera, EventPoseTracker
            >>> tracker = EventPoseTracker(Camera(64, 48, 60.0, 60.0, 31.5, 23.5), "box")
            >>> pose = torch.tensor([[0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
            >>> tracker.reset(pose)
            >>> refined, score = tracker.refine(pose, 0, 0)  # no events yet: an empty observation scores 0
            >>> tuple(refined.shape), score.tolist()
            ((1, 7), [0.0])
        """
        poses = torch.as_tensor(poses, dtype=torch.float64)
        if poses.ndim != 2 or poses.shape[1] != 7 or not 0 <= index < self.batch_size or rounds < 0:
            raise ValueError(f"expected poses (K, 7), 0 <= index < {self.batch_size} and rounds >= 0, got "
                             f"{tuple(poses.shape)}, {index}, {rounds}")
        renderer = self._renderers[self._renderer_of[index]]
        last = self._observed_us()[index:index + 1]
        surface, window = self.eros.surface[index:index + 1], self.recency.window_us[index:index + 1]
        t_now, max_age = torch.tensor([int(t_us)]), self.config.eros.max_age_us
        out, scores = poses.clone(), torch.full((len(poses),), -math.inf, dtype=torch.float64)
        for k in range(len(poses)):
            pose = out[k:k + 1]
            for r in range(rounds + 1):
                win = window_of(pose[:, :3].numpy(), self.camera, self._radius_of[index].item(),
                                self.config.render.margin_px, clip=True)[0]
                render = renderer.render(pose.float(), roi=tuple(win.tolist()))
                if not bool((render.depth > 0).any()):
                    break
                model = self.corrector.template_model(pose, render.depth, render.gray, tuple(win[:2].tolist()))
                canvas = model.depth.shape[-1]
                obs = canvas_observation(surface, last, model.box, canvas, t_now, max_age, window).reshape(1, -1)
                if r == rounds:
                    area = area_weight(obs[0].numpy(), model.valid[0].numpy(), canvas, float(model.interior[0]))
                    scores[k] = float(model.fit_canvas(obs).s0[0]) - area
                else:
                    pose = self.corrector.correct_canvas(model, pose, obs).pose.double()
            out[k] = pose[0]
        return out, scores

    def _follow(self, owner: "EventPoseTracker") -> None:
        """Share ``owner``'s event stages (burst guard, denoise filter, EROS, time surface, flow), which depend on the
        events only: ``owner`` takes each window in, and this tracker's update reads them after ``owner``'s
        (:meth:`forward` gives it the window's :class:`_Intake`). Its own recency windows follow the same flow."""
        self.burst, self.denoise, self.eros = owner.burst, owner.denoise, owner.eros
        self.time_surface, self.flow = owner.time_surface, owner.flow
        self._take_in_ahead = False
        self._run.bound = None

    @torch.inference_mode()
    def adopt(self, other: "EventPoseTracker", mask: torch.Tensor | None = None) -> None:
        """Take the motion state of the elements of ``mask`` (default all; ``(B,)`` bool or ``(K,)`` indices) from
        ``other``, a tracker of the same camera and meshes fed the same events (:mod:`torchevtrack.hypotheses`):
        their pose and previous pose, velocity filter, correction feedback, depth and where the next update renders;
        their UKF (if on) restarts at that pose with the velocity filter's twist. A tracker without a UKF then
        continues exactly as ``other`` does. The event stages (EROS, time surface, flow) depend on the events only and
        stay; so do the loss detector and the re-localiser. Call it between updates; a window taken in ahead keeps
        going (it reads the events only).
        """
        B = self.batch_size
        if not isinstance(other, EventPoseTracker) or other.batch_size != B or other.camera != self.camera:
            raise ValueError("adopt needs a tracker of the same camera and batch size")
        m = batch_mask(mask, B)
        if not bool(m.any()):
            return
        self._drop_render()
        self.velocity.take(other.velocity, m)
        if self.feedback is not None and other.feedback is not None:
            self.feedback.take(other.feedback, m)
        pose = torch.where(m[:, None], other.pose, self.pose)
        self.pose.copy_(pose)
        self.prev_pose[m] = other.prev_pose[m]
        self.depth_lag.masked_fill_(m, 0.0)  # the filter restarts at the adopted pose: measured and output agree
        self.ukf.reset(pose, shift_twist(self.velocity.x, -pose[:, :3]), m)  # the filter's twist is about the centre
        self._render_next[m] = other._render_next[m]  # where the next update renders (render.ahead)
        self._render_next_ok[m] = other._render_next_ok[m]
        H, W = self.camera.height, self.camera.width
        ho, wo = other.depth.shape[-2:]
        depth, origin = self._grown_depth(ho, wo)  # the other's depth rows, each placed where its window lies
        h, w = depth.shape[-2:]
        for i in m.nonzero()[:, 0].tolist():
            u0, v0 = other.origin[i].tolist()
            u1, v1 = min(u0, W - w), min(v0, H - h)
            depth[i] = 0.0
            depth[i, v0 - v1:v0 - v1 + ho, u0 - u1:u0 - u1 + wo] = other.depth[i]
            origin[i] = torch.tensor([u1, v1])
        self._set_depth(depth)
        self.origin.copy_(origin)
        self._run.models = None  # the template of the last render

    # -- offline tracking --------------------------------------------------------------------
    def track(
        self,
        streams: EventStream | Sequence[EventStream],
        initial_pose: torch.Tensor,
        t_start_us: int | Sequence[int] | None = None,
        t_end_us: int | Sequence[int] | None = None,
        progress: bool = True,
        return_lost: bool = False,
    ) -> tuple[torch.Tensor, ...]:
        """Track whole recordings; one stream per batch element, all advanced in lockstep.

        Args:
            streams: an :class:`EventStream` (B = 1) or ``B`` streams.
            initial_pose: ``(B, 7)`` or ``(7,)`` pose at ``t_start_us``.
            t_start_us, t_end_us: per-stream start / end times (default: first / last event).
            progress: show a tqdm bar.
            return_lost: also return the loss detector's flags (needs ``config.loss.enabled``).

        Returns:
            ``t_us (B, N)`` int64 update times (end of each window) and ``poses (B, N, 7)`` float64; with
            ``return_lost`` also ``lost (B, N)`` bool, :attr:`lost` after each update (an element the
            ``on_lost`` callback re-initialised is lost at that update and starts over from the next).
        """
        if return_lost and self.loss is None:
            raise ValueError("return_lost needs the loss detector: set loss.enabled in the config")
        if isinstance(streams, EventStream):
            streams = [streams]
        B = self.batch_size
        if len(streams) != B:
            raise ValueError(f"expected {B} event streams, got {len(streams)}")
        streams = [self._checked_stream(s, k) for k, s in enumerate(streams)]  # once: the updates skip the checks
        starts = _per_stream(t_start_us, [s.t_start for s in streams], "t_start_us")
        ends = _per_stream(t_end_us, [s.t_end for s in streams], "t_end_us")
        n = max((e - s) // self.period_us for s, e in zip(starts, ends))
        if n <= 0:
            raise ValueError("the streams are shorter than one update period")
        k = torch.arange(n + 1, dtype=torch.int64) * self.period_us
        bounds = [torch.searchsorted(s.t, st + k) for s, st in zip(streams, starts)]
        self.reset(initial_pose)
        times = torch.stack([st + k[1:] for st in starts])
        poses = torch.empty(B, n, 7, dtype=torch.float64)
        lost = torch.zeros(B, n, dtype=torch.bool)

        def window(i: int) -> tuple | None:
            return pack_streams([s[int(bd[i]): int(bd[i + 1])] for s, bd in zip(streams, bounds)]) if i < n else None

        ahead = window(0)
        try:
            for i in tqdm(range(n), desc="tracking", unit="update", disable=not progress, leave=False):
                current, ahead = ahead, window(i + 1)
                poses[:, i] = self(*current, t_us=times[:, i], next_window=ahead, check=False)
                if return_lost:
                    lost[:, i] = self.lost
        finally:
            self.drop_ahead()
        return (times, poses, lost) if return_lost else (times, poses)

    def _checked_stream(self, s: EventStream, k: int) -> EventStream:
        """Stream ``k`` checked as a whole (:func:`~torchevtrack.events.check_window`) and in the kernels' dtypes."""
        try:
            checked = check_window(s.x, s.y, s.t, s.p, width=self.camera.width, height=self.camera.height)[:4]
        except ValueError as e:
            raise ValueError(f"stream {k}: {e}") from None
        return s if all(c is f for c, f in zip(checked, (s.x, s.y, s.t, s.p))) else EventStream(*checked)

    # -- internals ---------------------------------------------------------------------------
    def _windows(self, poses: np.ndarray, index: list[int] | None = None) -> np.ndarray:
        """Render windows ``(K, 4)`` ``(u0, v0, w, h)`` of the elements ``index`` (default all) at ``poses`` ``(B, 7)``,
        clipped to the frame."""
        t, radius = poses[:, :3], self._radius_of.numpy()
        if index is not None:
            t, radius = t[index], radius[index]
        return window_of(t, self.camera, radius, self.config.render.margin_px, clip=True)

    def _render_into(self, i: int, pose: np.ndarray, win: np.ndarray, origin: np.ndarray, depth: np.ndarray,
                     gray: np.ndarray | None, model: bool = False) -> TemplateModel | None:
        """Render element ``i`` at the valid ``pose`` ``(1, 7)`` float64 in its own window ``win`` and write it into
        row ``i`` of the common-size buffers whose top-left pixel is ``origin`` ``(2,)`` (the own window lies inside).
        The compiled rasteriser goes through its unchecked binding (the workers render in parallel only inside its
        kernel: checks and tensor glue would hold the GIL), which finds the same window; with ``model`` (it needs the
        binding) it also makes the template model, returned, and writes no grey image."""
        u, v, w, h = win.tolist()
        du, dv = u - int(origin[0]), v - int(origin[1])
        bound = self._render_bindings[self._renderer_of[i]]
        if bound is not None:
            out = bound(pose, model or gray is not None, model)
        else:
            out = self._renderers[self._renderer_of[i]].render(torch.from_numpy(pose), roi=(u, v, w, h),
                                                               shaded=gray is not None)
        depth[i, dv:dv + h, du:du + w] = out.depth.numpy()[0]
        if gray is not None:
            gray[i, dv:dv + h, du:du + w] = out.gray.numpy()[0]
        return out.model if model else None

    def _render(self, poses: np.ndarray, shaded: bool):
        """Render each element in its own window around its pose (``poses`` ``(B, 7)`` float64), placed in buffers of
        one common size (the largest window; outside its own window an element's buffers hold background, as its window
        contains its object). A render's pixels depend slightly on its window, so own windows keep the
        elements from changing each other's renders. Keeps the depth and the windows' common ``origin``. With the
        compiled rasteriser a shaded render comes with each element's template model (made with its own render,
        :class:`~torchevtrack.update.RenderModelBinding`), one model per share of the batch."""
        B = self.batch_size
        H, W = self.camera.height, self.camera.width
        if B == 1 and self._render_one is not None:  # the own window is the common one: the render is the buffer
            if self._run.rendering is not None:  # made ahead, at these poses, with its template model (render.ahead)
                rendering, self._run.rendering = self._run.rendering, None  # taken, even if it failed
                made = self._render_one.finish(rendering.result())
            else:  # with its template model when shaded
                made = self._render_one(poses, shaded, shaded)
            self._set_depth(made.depth)
            self.origin.numpy()[:] = made.window[:, :2]
            return _Render(made.depth, made.gray, None if made.model is None else [made.model])
        if B == 1:
            win = self._windows(poses)
            out = self._renderers[0].render(torch.from_numpy(poses), roi=tuple(win[0].tolist()), shaded=shaded)
            self._set_depth(out.depth)
            self.origin.numpy()[:] = win[:, :2]
            return _Render(out.depth, out.gray)
        win = self._windows(poses)
        w, h = int(win[:, 2].max()), int(win[:, 3].max())
        origin = np.stack((np.minimum(win[:, 0], W - w), np.minimum(win[:, 1], H - h)), -1)
        depth = torch.zeros(B, h, w)
        # the compiled rasteriser's binding makes each element's template model with its render (its own render)
        modelled = shaded and all(b is not None for b in self._render_bindings)
        gray = torch.empty(B, h, w) if shaded and not modelled else None

        depth_np, gray_np = depth.numpy(), None if gray is None else gray.numpy()

        def share(rows: slice) -> TemplateModel | None:
            models = []
            for i in range(B)[rows]:
                if gray_np is not None:
                    gray_np[i] = self._renderers[self._renderer_of[i]].background
                models.append(self._render_into(i, poses[i:i + 1], win[i], origin[i], depth_np, gray_np, modelled))
            return _cat(models) if modelled else None

        models = self._schedule.map(share) if self._threaded_render else [share(slice(None))]
        self._set_depth(depth)
        self.origin.copy_(torch.from_numpy(origin))
        return _Render(depth, gray, models if modelled else None)

    def _bind(self) -> "_Bound":
        """Bind each stage's compiled step to the buffers it reads and writes (numpy views: no checks or conversions
        per update), per worker share where the workers run it (one worker: its share is the whole batch)."""
        cfg, o, e = self.config, self.corrector.options, self.config.eros
        fb = self.feedback
        dt = periods(self.batch_size, self.dt)
        motion = MotionArgs(cfg.velocity.source, self.pose.numpy(), self.prev_pose.numpy(), dt, self._min_depth.numpy(),
                            self.velocity.arrays(), cfg.flow.max_speed,
                            max(cfg.flow.block // 4, 2),  # flow lies on edges: the pixel may fall just off
                            None if fb is None else fb.b.numpy())
        times = self._observed_us()
        correct = [bind_correction(self.eros.surface[r].numpy(), times[r].numpy(), self.camera, canvas=o["canvas"],
                                   margin_px=o["margin_px"], edge_clip=o["edge_clip"], silhouette=o["silhouette"],
                                   interior=o["interior"], dp_px=o["dp_px"], dtheta_deg=o["dtheta_deg"], rule=o["rule"],
                                   iterations=o["iterations"], max_dz=cfg.template.max_depth_speed * self.dt,
                                   max_age_us=e.max_age_us,
                                   recency=self.recency.arrays(e.max_age_us, r))
                   for r in self._schedule.shares]
        output = OutputArgs(self.pose.numpy(), dt, self._min_depth.numpy(), self.depth_lag.numpy(),
                            self.ukf.arrays() if cfg.ukf.enabled else None, None if fb is None else fb.arrays())
        observe = None if self.time_surface is None else \
            bind_observe(self.eros, self.time_surface, self.recency.arrays(e.max_age_us), canvas=o["canvas"],
                         max_age_us=e.max_age_us)
        intake = [bind_intake(self.eros, self.time_surface, self.flow, r) for r in self._schedule.shares]
        self._run.bound = _Bound(intake, motion, correct, output, observe, self.recency.bind(),
                             self.pose.numpy(), self.prev_pose.numpy(), self.origin.numpy(), self.events_seen.numpy(),
                             self.t_last.numpy(), self._min_depth.numpy(), self._render_next.numpy(),
                             self._render_next_ok.numpy())
        return self._run.bound

    def _apply(self, fn, recurse=True):
        """Refuse a conversion (``.to``, ``.float``, ``.double``, ``.half``, ``.cuda``, ...) that would change a
        tensor's dtype or move it off the CPU: the compiled kernels take the tracker's own dtypes on the CPU."""
        for dtype in (torch.float64, torch.float32):
            try:
                out = fn(torch.zeros(1, dtype=dtype))
            except Exception as e:  # e.g. .cuda() on a CPU-only build
                raise ValueError(f"EventPoseTracker runs on the CPU in its own dtypes (float64 poses and filters, "
                                 f"float32 images), so it cannot be converted or moved: {e}") from None
            if not isinstance(out, torch.Tensor):
                continue
            if out.dtype != dtype or out.device.type != "cpu":
                raise ValueError(f"EventPoseTracker runs on the CPU in its own dtypes (float64 poses and filters, "
                                 f"float32 images), so it cannot be converted or moved to {out.dtype} on {out.device}")
        self._run.bound = None  # the buffers may be new tensors: bind again
        return super()._apply(fn, recurse)

    def _settle(self, what: str) -> None:
        """Before the state is read or replaced (``what``): no window may be taken in ahead (its events are half in the
        stages), and a render made ahead must be done (it reads the poses)."""
        if self._run.ahead is not None:
            raise RuntimeError(f"cannot {what} while a window is taken in ahead (forward(next_window=...)): "
                               "do it after the update of that window")
        if self._run.rendering is not None:
            self._run.rendering.wait()

    def __getstate__(self) -> dict:
        """The attributes for a copy or pickle: the transient scheduling state (the pipeline's thread, a render made
        ahead, the compiled steps bound to the buffers, the worker pool) is left out and made again when needed."""
        self._settle("copy or pickle the tracker")
        state = super().__getstate__()  # a copy of the attributes
        state["_run"] = dataclasses.replace(self._run, bound=None, rendering=None, observing=None)
        return state

    def _save_to_state_dict(self, destination, prefix, keep_vars):
        self._settle("take the state_dict")
        super()._save_to_state_dict(destination, prefix, keep_vars)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        """Load the buffers of another tracker of the same camera, meshes and configuration, used or not: the depth
        buffer takes the size of the loaded one (it follows the object's window), and the transient state (the
        pipeline's work ahead, the bound steps, the last template model) is dropped and made again when needed."""
        self._settle("load a state_dict")
        self._run = _UpdateState(self._run.quality)  # (a render made ahead is forgotten: the next update renders)
        depth = state_dict.get(prefix + "depth")
        if isinstance(depth, torch.Tensor) and depth.ndim == 3 and depth.shape[0] == self.batch_size:
            self._set_depth(torch.zeros(depth.shape, dtype=self.depth.dtype))  # an ordinary tensor: copy_ may write it
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    def _render_pose_ahead(self, predicted: np.ndarray, twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """render.ahead: the poses to render at now (where the last update's prediction, moved on by its twist,
        was valid; else ``predicted``), float64 and float32, and the next update's in the buffers (:func:`propagate`
        of ``predicted`` and ``twist``, and whether it is valid)."""
        B, run = self.batch_size, self._run.bound
        now, now32 = np.empty((B, 7)), np.empty((B, 7), dtype=np.float32)
        render_ahead(predicted, twist, periods(B, self.dt), run.min_depth, run.render_next, run.render_next_ok,
                     now, now32)
        return now, now32

    def _render_soon(self, poses: np.ndarray, shaded: bool, model: bool) -> None:
        """Make the next update's render at ``poses`` and, with ``model``, its template model on the intake thread
        (one element, compiled rasteriser), in one compiled call
        (:class:`~torchevtrack.update.RenderModelBinding`)."""
        if self._render_one is not None:  # only the compiled call on that thread: it needs the GIL only to start
            r = self._render_one
            self._run.rendering = self._schedule.submit(r.kernel, *r.start(poses, shaded, model))

    def _drop_render(self) -> None:
        """Forget a render made ahead (a reset moved the poses): wait for the thread."""
        if self._run.rendering is not None:
            self._run.rendering.wait()
            self._run.rendering = None

    def _render_depth(self, poses: torch.Tensor, mask: torch.Tensor) -> None:
        """Render the depth of the ``mask`` elements at ``poses`` ``(B, 7)`` into the depth buffer.

        The others keep their depth values and origins: if a selected element needs a larger window, the
        common size grows and their windows are zero-padded into it (exact: their objects lie inside).
        """
        index = mask.nonzero()[:, 0].tolist()
        if not index:
            return
        H, W = self.camera.height, self.camera.width
        win = self._windows(poses.numpy(), index)
        depth, origin = self._grown_depth(int(win[:, 3].max()), int(win[:, 2].max()))
        h, w = depth.shape[-2:]
        for i, wi in zip(index, win):
            origin[i] = torch.tensor([min(wi[0], W - w), min(wi[1], H - h)])
            depth[i] = 0.0
            self._render_into(i, poses.numpy()[i:i + 1], wi, origin[i].numpy(), depth.numpy(), None)
        self._set_depth(depth)
        self.origin.copy_(origin)

    def _grown_depth(self, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The depth buffer and origins grown to hold a window of at least ``h`` x ``w`` pixels (the buffer itself if it
        does): each element's rows zero-padded into the larger common size, its origin moved to keep them in the
        frame."""
        H, W = self.camera.height, self.camera.width
        h0, w0 = self.depth.shape[-2:]
        h, w = max(h, h0), max(w, w0)
        origin = self.origin.clone()
        if (h, w) == (h0, w0):
            return self.depth, origin
        origin[:, 0].clamp_(max=W - w)
        origin[:, 1].clamp_(max=H - h)
        depth = self.depth.new_zeros(self.batch_size, h, w)
        for i, ((u0, v0), (u1, v1)) in enumerate(zip(self.origin.tolist(), origin.tolist())):
            depth[i, v0 - v1:v0 - v1 + h0, u0 - u1:u0 - u1 + w0] = self.depth[i]
        return depth, origin

    def _guard(self, window: tuple) -> tuple[tuple, np.ndarray, np.ndarray, np.ndarray | None]:
        """The burst guard, then the denoise filter if on, on a packed ``window`` ``(x, y, t, p, b)``: its kept events
        (the window itself when nothing is dropped), each element's events in the window and kept ``(B,)`` int64, and
        the burst flags ``(B,)`` bool (``None``: no guard). A window judged ahead (:meth:`_guard_ahead`) is not judged
        again."""
        g = self._run.guarded
        if g is not None and g[0] is window[0]:
            self._run.guarded = None
            return g[1:]
        self._run.guarded = None
        x, b = window[0], window[4]
        counts = np.bincount(b.numpy(), minlength=self.batch_size) if b is not None else \
            np.full(self.batch_size, x.numel(), dtype=np.int64)
        burst, seen = None, counts
        if self.burst is not None:
            burst = self.burst(counts, self.period_us).numpy()
            if burst.any():
                k = keep_events(b, x.numel(), torch.from_numpy(burst))
                window, seen = tuple(None if f is None else f[k] for f in window), np.where(burst, 0, counts)
        if self.denoise is not None and window[0].numel():
            k = self.denoise(window[0], window[1], window[2], window[4])
            window = tuple(None if f is None else f[k] for f in window)
            seen = np.bincount(window[4].numpy(), minlength=self.batch_size) if window[4] is not None else \
                np.full(self.batch_size, window[0].numel(), dtype=np.int64)
        return window, counts, seen, burst

    def _guard_ahead(self, window: tuple) -> tuple:
        """Judge the next ``window``, known ahead, now (after this one: the guard's state runs in window order); its
        kept events, which go in ahead; the next update takes its verdict (it is called with the same ``x``)."""
        kept, counts, seen, burst = self._guard(window)
        self._run.guarded = (window[0], kept, counts, seen, burst)
        return kept

    def _t_now(self, t: torch.Tensor, b: torch.Tensor | None) -> np.ndarray:
        """Latest event time per element in this window (int64 us, the view of :attr:`t_last` the update binds; the
        previous one if the window is empty)."""
        last = self._run.bound.t_last
        if t.numel():
            if b is None:
                np.maximum(last, t.numpy().max(), out=last)
            else:
                np.maximum.at(last, b.numpy(), t.numpy())
        return last

    @staticmethod
    def _feedback_on(cfg: TrackerConfig) -> bool:
        """The correction feedback runs (it needs the flow twist and the corrections; only it uses symmetry axes)."""
        v = cfg.velocity
        return v.source == "flow" and cfg.template.enabled and v.feedback_gain > 0

    def _correct(self, predicted: np.ndarray, z_ref: np.ndarray, pose32: np.ndarray, render: "_Render | None",
                 t_now: np.ndarray, on_observed: Callable[[], object] | None = None,
                 obs: np.ndarray | None = None) -> Correction:
        """Template correction of the ``predicted`` poses, their depths bounded around ``z_ref`` ``(B,)``, with a new
        template model of ``render`` (made at ``pose32``), or the last model when ``render`` is ``None``; each worker
        corrects its share of the batch. ``on_observed`` (only without workers) is called once the EROS and the time
        surface have been read. ``obs``: the observation made on the intake thread under the last model's box (one
        element, ``render`` ``None``)."""
        if render is None:
            def share(rows: slice, correct: Callable[..., CorrectionStep], model: TemplateModel) -> CorrectionStep:
                return correct(None, _cut(predicted, rows), None, None, None, _cut(t_now, rows), model=model,
                               on_observed=on_observed, obs=obs, z_ref=_cut(z_ref, rows))

            parts = self._schedule.map(share, self._run.bound.correct, self._run.models)
        else:
            depth, gray = render.depth.numpy(), None if render.gray is None else render.gray.numpy()

            def share(rows: slice, correct: Callable[..., CorrectionStep]) -> CorrectionStep:
                return correct(_cut(pose32, rows), _cut(predicted, rows), _cut(depth, rows), _cut(gray, rows),
                               _cut(self._run.bound.origin, rows), _cut(t_now, rows), on_observed=on_observed,
                               z_ref=_cut(z_ref, rows))

            parts = self._schedule.map(share, self._run.bound.correct)
        self._run.models = [p.model for p in parts]  # kept per share: each worker reads its own next time
        return _cat([p.correction for p in parts])

    def _observe_soon(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, b: np.ndarray | None,
                      t_now: np.ndarray) -> None:
        """Take the checked events into the EROS and the time surface on the intake thread and observe them under the
        canvas box of the render made ahead there (:func:`~torchevtrack.stages.eros.bind_observe`), for
        :meth:`_correct`."""
        rendering, observe, box = self._run.rendering, self._run.bound.observe, self._render_one.observed_box

        def job() -> np.ndarray | None:
            # the render, the job before this one on the thread, wrote the box of its model; if it failed, the update
            # raises that when it takes the render, and the events still go in
            return observe(x, y, t, b, None if rendering.raised() else box, t_now)

        self._run.observing = self._schedule.submit(job)

    def _launch(self, window: tuple) -> None:
        """Take the packed ``window`` into the EROS and the flow on the intake thread (:meth:`_take_ahead` waits)."""
        self._run.ahead = _Ahead(self._schedule.submit(self._run.bound.intake[0], *window), window)

    def _take_ahead(self, x: torch.Tensor) -> FlowField:
        """The flow of the window the intake thread took in, once it is done; ``x`` is that window's."""
        ahead, self._run.ahead = self._run.ahead, None
        flow = ahead.flow.result()
        if ahead.window[0] is not x:
            raise RuntimeError("the update is not for the window taken in ahead (an interrupted track or push?)")
        return flow

    def _retake_ahead(self, m: torch.Tensor) -> None:
        """After a reset of the elements ``m`` ``(B,)`` bool: take their events of the window already taken in
        ahead into their cleared EROS and flow again (the others keep theirs), as if the reset came first."""
        x, y, t, p, b = self._run.ahead.window
        parts = list(self._run.ahead.flow.result())
        for i in m.nonzero()[:, 0].tolist():
            k = slice(None) if b is None else b == i
            redo = bind_intake(self.eros, self.time_surface, self.flow, slice(i, i + 1))(
                x[k], y[k], t[k], p[k], None if b is None else b[k] - i)
            for field, row in zip(parts, redo):
                field[i] = row[0]
        self._run.ahead = _Ahead(Job.of(FlowField(*parts)), self._run.ahead.window)


@dataclass
class _UpdateState:
    """What one update leaves for the next, none of it a parameter, buffer or submodule (a plain object, so that
    setting these costs no nn.Module bookkeeping).

    quality: the last update's :class:`Quality` (or its fields as numpy arrays until read); ahead: the next window,
    taken in on the intake thread; guarded: the next window as the burst guard judged it ahead (its original ``x``, its
    kept events, counts and flags); rendering: render.ahead, the next update's render and model on the intake thread;
    observing: streaming, this update's EROS, time surface and observation there; models: the template of the last
    render, one per worker's share; bound: the stages' compiled steps bound
    to the tracker's buffers (made on first use); loss_report: the last update's :class:`~torchevtrack.loss.LossUpdate`
    (``True``: the detector ran, the report is made when read; ``None``: no update since the last full reset).
    """
    quality: "Quality | tuple"
    ahead: "_Ahead | None" = None
    rendering: Job | None = None
    observing: Job | None = None
    guarded: tuple | None = None
    models: "list[TemplateModel] | None" = None
    bound: "_Bound | None" = None
    loss_report: "LossUpdate | bool | None" = None


class _Intake(NamedTuple):
    """A window as the event stages took it (:meth:`EventPoseTracker._intake`): its kept events ``(x, y, t, p, b)``,
    its flow field, each element's events in the window and kept ``(B,)`` int64, the burst flags ``(B,)`` bool (or
    ``None``), and ``launch``: takes the next window in, once the update has read the surfaces (or ``None``)."""
    window: tuple
    flow: FlowField
    counts: np.ndarray
    seen: np.ndarray
    burst: np.ndarray | None
    launch: Callable[[], None] | None


@dataclass
class _Ahead:
    """A window ``(x, y, t, p, b)`` taken into the EROS and the flow ahead of its update, and its flow field."""
    flow: Job
    window: tuple


class _Bound(NamedTuple):
    """The stages' bound steps (:meth:`EventPoseTracker._bind`; ``intake`` and ``correct`` one per worker share) and
    numpy views of the tracker's buffers an update reads and writes."""
    intake: list[Callable[..., FlowField]]
    motion: MotionArgs
    correct: list[Callable[..., CorrectionStep]]
    output: OutputArgs
    observe: Callable[..., np.ndarray | None | bool] | None
    recency: Callable[[np.ndarray, np.ndarray], None]
    pose: np.ndarray
    prev_pose: np.ndarray
    origin: np.ndarray
    events_seen: np.ndarray
    t_last: np.ndarray
    min_depth: np.ndarray
    render_next: np.ndarray
    render_next_ok: np.ndarray


@dataclass
class _Render:
    depth: torch.Tensor
    gray: torch.Tensor | None
    models: list[TemplateModel] | None = None  # its template models, one per share, when made with it


_T = TypeVar("_T")
_ALL = slice(None)  # every row: the share of a single worker


def _cut(v: np.ndarray | None, rows: slice) -> np.ndarray | None:
    """A share's rows of a batch-leading array (all rows, or ``None``: as it is)."""
    return v if v is None or rows == _ALL else v[rows]


def _cat(parts: list[_T]) -> _T:
    """Named tuples of batch-leading tensors or numpy arrays, concatenated field by field (the only one as it is)."""
    if len(parts) == 1:
        return parts[0]
    return type(parts[0])(*(np.concatenate(f) if isinstance(f[0], np.ndarray) else torch.cat(f) for f in zip(*parts)))


def _per_stream(value, default: list[int], name: str) -> list[int]:
    if value is None:
        return default
    if isinstance(value, int):
        return [value] * len(default)
    if len(value) != len(default):
        raise ValueError(f"{name} needs one value per stream ({len(default)}), got {len(value)}")
    return [int(v) for v in value]

