"""Watch a tracker in the rerun viewer: :class:`RerunLogger`, called by the tracker after every update.

The logger is a forward hook of an :class:`~torchevtrack.tracker.EventPoseTracker` (:meth:`RerunLogger.attach`):
after each update it logs, for one batch element, on the timelines ``time`` (the update's time stamp, the window
end) and ``update`` (its index):

==============================  ========================================================================
``world/camera``                the event camera (pinhole ``K``, OpenCV axes: x right, y down, z forward)
``world/camera/eros``           the EROS surface (grey, 0-255), every ``image_period_us``
``world/camera/eros/tracked``   the model's silhouette at the tracked pose (green line segments), same rate
``world/camera/eros/truth``     the same at the true pose, when a ground truth is given (magenta)
``world/object``                the tracked pose (a rigid transform, camera frame)
``world/object/mesh``           the object mesh, moved by that transform
``world/trajectory/tracked``    the tracked object centre so far (a 3D line strip); ``world/trajectory/truth``:
                                the ground truth's (static)
``errors/translation_cm``       ``|t - t_gt|`` (cm) and ``errors/rotation_deg`` the geodesic rotation error
                                (deg) against the ground truth interpolated at the update time
``timing/<stage>_ms``           the tracker's ``stage_ms`` (eros, flow, velocity, render, correction, ukf, ...)
``quality/score``               the template score, ``quality/flow_vectors``, ``quality/events``
``loss/lost``                   1 while the loss detector holds the element lost (with a detector);
                                ``quality/rejected`` 1 when the update's pose was rejected
==============================  ========================================================================

The images are logged at once; the series (the pose, errors, timings, quality, loss) are buffered and sent in
columns every 50 updates and at :meth:`close` (one call per entity instead of one per update and entity: the
logging then costs well under 1 ms per update instead of about 8), so a live viewer shows them up to 50 updates late.

The silhouette is the set of mesh edges between a face turned to the camera and one turned away (no occlusion
test: for a non-convex object, hidden silhouette edges are drawn too). With the tracker's pipeline the intake
thread may already be taking the next window into the EROS while an update is logged: the image can hold some of
its events.

rerun is an optional dependency: ``pip install 'torchevtrack[rerun]'``.

Example (``tracker`` an :class:`~torchevtrack.tracker.EventPoseTracker` of that camera and mesh)::

    from torchevtrack.watch import RerunLogger
    logger = RerunLogger(camera, "can", path="run.rrd", gt=(gt_t_us, gt_poses)).attach(tracker)
    tracker.track(events, pose0)
    logger.close()          # the recording is complete: rerun run.rrd
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import interpolate_poses, quat_to_matrix
from torchevtrack.mesh import load_mesh
from torchevtrack.metrics import pose_errors

__all__ = ["RerunLogger", "silhouette_segments"]

TRACKED_COLOUR = (0, 255, 0)
TRUTH_COLOUR = (255, 0, 255)
_STRIP_EVERY = 50


def silhouette_segments(mesh, pose: torch.Tensor, camera: Camera) -> np.ndarray:
    """Image segments of the mesh silhouette at ``pose``: the edges between a face turned to the camera and one
    turned away, projected with the camera's pinhole ``K`` (no occlusion test).

    Args:
        mesh: a ``trimesh.Trimesh`` (metres, closed: every edge shared by two faces).
        pose: ``(7,)`` ``[tx, ty, tz, qw, qx, qy, qz]``, object in camera frame.
    Returns:
        ``(S, 2, 2)`` float32 pixel coordinates ``(u, v)`` of each segment's two ends.
    """
    pose = torch.as_tensor(pose, dtype=torch.float64)
    R = quat_to_matrix(pose[3:]).numpy()
    v = np.asarray(mesh.vertices) @ R.T + pose[:3].numpy()
    n = np.asarray(mesh.face_normals) @ R.T
    centre = v[np.asarray(mesh.faces)].mean(axis=1)
    front = (n * centre).sum(-1) < 0
    adj = np.asarray(mesh.face_adjacency)
    edges = np.asarray(mesh.face_adjacency_edges)[front[adj[:, 0]] != front[adj[:, 1]]]
    ends = v[edges]  # (S, 2, 3)
    ends = ends[(ends[..., 2] > 1e-6).all(-1)]
    uv = np.stack((camera.fx * ends[..., 0] / ends[..., 2] + camera.cx,
                   camera.fy * ends[..., 1] / ends[..., 2] + camera.cy), axis=-1)
    return uv.astype(np.float32)


class RerunLogger:
    """Logs a tracker's updates to a rerun recording (see the module docstring for the entities).

    Args:
        camera: the tracker's camera.
        mesh: the object's mesh (path, built-in / YCB name or trimesh), as given to the tracker.
        path: write the recording to this ``.rrd`` file; spawn: stream it to a rerun viewer started now (both
            may be given; at least one).
        gt: optional ground truth ``(t_us (G,) int64, poses (G, 7))`` for the true contour, trajectory and errors.
        element: the batch element to log (default 0).
        image_period_us: log the EROS image and contours at most this often (default 20 ms: 50 frames per
            second of the sequence); everything else is logged every update.
        name: the recording's application id.
    """

    def __init__(self, camera: Camera, mesh, *, path: str | Path | None = None, spawn: bool = False,
                 gt: tuple[torch.Tensor, torch.Tensor] | None = None, element: int = 0,
                 image_period_us: int = 20_000, name: str = "torchevtrack") -> None:
        try:
            import rerun as rr
        except ImportError:
            raise ValueError("logging to rerun needs the rerun SDK: pip install 'torchevtrack[rerun]'") from None
        if path is None and not spawn:
            raise ValueError("RerunLogger needs a path to write, spawn=True, or both")
        if isinstance(element, bool) or not isinstance(element, int) or element < 0:
            raise ValueError(f"element must be a batch index >= 0, got {element!r}")
        if not image_period_us >= 0:
            raise ValueError(f"image_period_us must be >= 0, got {image_period_us!r}")
        self._rr = rr
        self.camera, self.element, self.image_period_us = camera, element, int(image_period_us)
        self.mesh = load_mesh(mesh)
        self.gt = None
        if gt is not None:
            gt_t, gt_p = torch.as_tensor(gt[0], dtype=torch.int64), torch.as_tensor(gt[1], dtype=torch.float64)
            if gt_t.ndim != 1 or gt_p.shape != (gt_t.numel(), 7) or gt_t.numel() == 0:
                raise ValueError(f"gt must be (t_us (G,), poses (G, 7)), got {tuple(gt_t.shape)}, {tuple(gt_p.shape)}")
            self.gt = (gt_t, gt_p)
        self.rec = rr.RecordingStream(name)
        if path is not None:
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
        if spawn:
            self.rec.spawn(connect=path is None)
            if path is not None:  # both: the file and the viewer
                self.rec.set_sinks(rr.FileSink(str(path)), rr.GrpcSink())
        else:
            self.rec.save(path)
        self.path = path
        self.updates = 0
        self._last_image_us: int | None = None
        self._centres: list[np.ndarray] = []
        self._pending: list[tuple[int, int, dict]] = []  # updates not sent yet: (t_us, index, series)
        self._handle = None
        self._log_static()

    # -- setup -------------------------------------------------------------------------------
    def _log_static(self) -> None:
        rr, rec, cam, m = self._rr, self.rec, self.camera, self.mesh
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        rec.log("world/camera", rr.Pinhole(image_from_camera=cam.K().numpy(), resolution=[cam.width, cam.height],
                                           camera_xyz=rr.ViewCoordinates.RDF), static=True)
        rec.log("world/object/mesh", rr.Mesh3D(vertex_positions=np.asarray(m.vertices, dtype=np.float32),
                                               triangle_indices=np.asarray(m.faces, dtype=np.uint32),
                                               vertex_normals=np.asarray(m.vertex_normals, dtype=np.float32)),
                static=True)
        if self.gt is not None:
            rec.log("world/trajectory/truth", rr.LineStrips3D([self.gt[1][:, :3].numpy()], colors=[TRUTH_COLOUR]),
                    static=True)

    def attach(self, tracker) -> "RerunLogger":
        """Register as a forward hook of ``tracker`` (an :class:`~torchevtrack.tracker.EventPoseTracker`, whose
        :meth:`~torchevtrack.tracker.EventPoseTracker.track` and :class:`~torchevtrack.online.OnlineTracker`
        call it per update); returns ``self``. :meth:`close` removes the hook."""
        if self.element >= tracker.batch_size:
            raise ValueError(f"element {self.element} is not in the tracker's batch of {tracker.batch_size}")
        self._handle = tracker.register_forward_hook(self, with_kwargs=True)
        return self

    # -- per update --------------------------------------------------------------------------
    def __call__(self, tracker, args: tuple, *rest) -> None:
        """The forward hook: ``(tracker, args, kwargs, output)`` (``with_kwargs=True``) or ``(tracker, args,
        output)``. The update time is the call's ``t_us`` (the window end), else the element's latest event."""
        kwargs, output = rest if len(rest) == 2 else ({}, rest[0])
        t = kwargs.get("t_us", args[5] if len(args) > 5 else None)
        t = torch.as_tensor(tracker.t_last if t is None else t).reshape(-1)
        self.log_update(int(t[self.element] if t.numel() > 1 else t[0]), output[self.element], tracker)

    def log_update(self, t_us: int, pose: torch.Tensor, tracker=None) -> None:
        """Log one update: the pose ``(7,)`` at ``t_us``; with ``tracker`` also its EROS, timings, quality and loss
        flags (its public state after that update). The series (pose, errors, timings, quality, loss) are sent in
        columns every 50 updates and at :meth:`close`; the images at once."""
        rr, rec, i = self._rr, self.rec, self.element
        pose = torch.as_tensor(pose, dtype=torch.float64)
        series = {"pose": pose.numpy().copy()}
        if tracker is not None:
            quality = tracker.quality
            series.update({f"timing/{stage}_ms": float(ms) for stage, ms in tracker.stage_ms.items()})
            series.update({"quality/score": float(quality.score[i]),
                           "quality/flow_vectors": float(quality.flow_vectors[i]),
                           "quality/events": float(quality.events[i]),
                           "quality/rejected": float(bool(quality.rejected[i]))})
            if tracker.lost is not None:
                series["loss/lost"] = float(bool(tracker.lost[i]))
        self._pending.append((int(t_us), self.updates, series))
        self._centres.append(series["pose"][:3])
        if self._last_image_us is None or t_us - self._last_image_us >= self.image_period_us:
            self._last_image_us = t_us
            rec.set_time("time", duration=np.timedelta64(int(t_us), "us"))
            rec.set_time("update", sequence=self.updates)
            if tracker is not None:
                img = (tracker.eros.surface[i].clamp(0, 1) * 255).to(torch.uint8).numpy()
                rec.log("world/camera/eros", rr.Image(img, color_model="L"))
            rec.log("world/camera/eros/tracked", rr.LineStrips2D(silhouette_segments(self.mesh, pose, self.camera),
                                                                colors=[TRACKED_COLOUR], radii=0.5))
            truth = self._truth(torch.tensor([int(t_us)]))
            if truth is not None and len(truth[0]):
                rec.log("world/camera/eros/truth", rr.LineStrips2D(
                    silhouette_segments(self.mesh, truth[1][0], self.camera), colors=[TRUTH_COLOUR], radii=0.5))
        self.updates += 1
        if self.updates % _STRIP_EVERY == 0:
            self._send_series()

    def _truth(self, t_us: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Which of the times ``(N,)`` lie in the ground truth's range (``(N,)`` bool) and the true poses there."""
        if self.gt is None:
            return None
        inside = (t_us >= self.gt[0][0]) & (t_us <= self.gt[0][-1])
        return inside, interpolate_poses(self.gt[0], self.gt[1], t_us[inside])

    def _send_series(self) -> None:
        """Send the buffered updates' series as columns, and the tracked trajectory so far."""
        if not self._pending:
            return
        rr, rec = self._rr, self.rec
        t_us = torch.tensor([p[0] for p in self._pending], dtype=torch.int64)
        updates = np.array([p[1] for p in self._pending], dtype=np.int64)
        rows = [p[2] for p in self._pending]
        self._pending = []

        def send(path: str, keep: np.ndarray, columns) -> None:
            times = [rr.TimeColumn("time", duration=t_us.numpy()[keep].astype("timedelta64[us]")),
                     rr.TimeColumn("update", sequence=updates[keep])]
            rec.send_columns(path, indexes=times, columns=columns)

        everything = np.ones(len(rows), dtype=bool)
        poses = np.stack([r["pose"] for r in rows])
        send("world/object", everything, rr.Transform3D.columns(translation=poses[:, :3],
                                                                quaternion=poses[:, [4, 5, 6, 3]]))
        truth = self._truth(t_us)
        if truth is not None and bool(truth[0].any()):
            inside = truth[0].numpy()
            e = pose_errors(torch.from_numpy(poses[inside]), truth[1])
            send("errors/translation_cm", inside, rr.Scalars.columns(scalars=e["te"].numpy() * 100.0))
            send("errors/rotation_deg", inside, rr.Scalars.columns(scalars=np.degrees(e["re"].numpy())))
        for key in dict.fromkeys(k for r in rows for k in r if k != "pose"):
            have = np.array([key in r for r in rows])
            send(key, have, rr.Scalars.columns(scalars=np.array([r[key] for r in rows if key in r])))
        rec.log("world/trajectory/tracked", rr.LineStrips3D([np.stack(self._centres)], colors=[TRACKED_COLOUR]))

    def close(self) -> None:
        """Log the whole tracked trajectory, remove the hook and flush the recording (the file is complete)."""
        if self._handle is not None:
            self._handle.remove()
            self._handle = None
        self._send_series()
        self.rec.flush()
        self.rec.disconnect()

    def __enter__(self) -> "RerunLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
