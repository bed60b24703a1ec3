"""Synthetic event sequences: trajectory -> shaded renders -> ESIM events, with ground truth.

Pipeline of :func:`generate_sequence`:

1. A seeded trajectory (:func:`torchevtrack.synth.trajectory.make_trajectory`), sampled every 100 us.
2. Frame times chosen adaptively: a new frame once the projected mesh bounding-box corners have moved
   ``max_px_per_frame`` pixels (summed over the dense samples, max over corners) since the last one.
3. Each frame renders only the region of interest (the union of the projected boxes at the previous
   and the current pose, plus 3 px) in front of a static uniform grey background; the ESIM updates
   that window only (every other pixel is unchanged, so it cannot emit).
4. Ground truth at ``gt_rate_hz`` (500 Hz) from the same trajectory.

Example:
    >>> from torchevtrack.camera import Camera
    >>> seq = generate_sequence("can", "regular", 0.05, seed=0, camera=Camera(64, 48, 50, 50, 31.5, 23.5),
    ...                         progress=False)       # doctest: +SKIP
    >>> seq.save("out/can_regular")                   # doctest: +SKIP
"""

from __future__ import annotations

import math

import numpy as np
import torch
from tqdm import tqdm

import torchevtrack
from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.geometry import interpolate_poses, transform_points
from torchevtrack.mesh import load_mesh
from torchevtrack.render import Renderer
from torchevtrack.synth.esim import ESIM
from torchevtrack.synth.sequence import Sequence
from torchevtrack.synth.trajectory import bbox_corners, make_trajectory, motion_stats, projected_bbox

__all__ = ["frame_times", "roi_union", "generate_sequence"]

_ROI_MARGIN = 3


def frame_times(t_us: torch.Tensor, poses: torch.Tensor, camera: Camera, corners: torch.Tensor,
                max_px: float = 0.5) -> torch.Tensor:
    """Indices of the trajectory samples to render so the image moves at most ``max_px`` between frames.

    The motion between consecutive samples is the largest displacement of the projected ``corners``;
    frames are picked greedily (the last sample still within ``max_px`` of accumulated motion). The first
    and last samples are always frames; a single sample step larger than ``max_px`` still gives one frame.

    Shape: ``(N,), (N, 7), camera, (M, 3) -> (F,)`` int64 indices.
    """
    if not max_px > 0:
        raise ValueError(f"max_px must be positive, got {max_px}")
    R_uv = _project_corners(poses, camera, corners)
    step = torch.linalg.norm(torch.diff(R_uv, dim=0), dim=-1).amax(-1)
    D = np.concatenate(([0.0], np.cumsum(step.numpy())))
    idx = [0]
    n = len(D)
    while idx[-1] < n - 1:
        k = int(np.searchsorted(D, D[idx[-1]] + max_px, side="right")) - 1
        idx.append(min(max(k, idx[-1] + 1), n - 1))
    return torch.tensor(idx, dtype=torch.int64)


def _project_corners(poses: torch.Tensor, camera: Camera, corners: torch.Tensor) -> torch.Tensor:
    return camera.project(transform_points(poses, corners.to(poses.dtype)))


def roi_union(boxes: torch.Tensor, camera: Camera, margin: int = _ROI_MARGIN) -> tuple[int, int, int, int]:
    """Integer window ``(u0, v0, w, h)`` covering image boxes ``(K, 4)`` ``[u_min, v_min, u_max, v_max]``
    plus ``margin`` pixels, clipped to the sensor."""
    u0 = max(int(math.floor(float(boxes[:, 0].min()))) - margin, 0)
    v0 = max(int(math.floor(float(boxes[:, 1].min()))) - margin, 0)
    u1 = min(int(math.ceil(float(boxes[:, 2].max()))) + margin, camera.width - 1)
    v1 = min(int(math.ceil(float(boxes[:, 3].max()))) + margin, camera.height - 1)
    if u1 < u0 or v1 < v0:
        raise ValueError("the object is outside the image")
    return u0, v0, u1 - u0 + 1, v1 - v0 + 1


def generate_sequence(
    object_name: str,
    motion: str,
    duration_s: float,
    seed: int,
    camera: Camera | None = None,
    *,
    C: float = 0.2,
    sigma_C: float = 0.03,
    refractory_us: int = 0,
    noise_rate_hz: float = 0.0,
    background: float = 0.2,
    max_px_per_frame: float = 0.5,
    gt_rate_hz: int = 500,
    render_faces: int | None = None,
    progress: bool = True,
) -> Sequence:
    """Simulate one sequence.

    Args:
        object_name: mesh name or path for :func:`torchevtrack.mesh.load_mesh`.
        motion: ``"regular"`` or ``"fast"``.
        duration_s: seconds.
        seed: seeds the trajectory and the simulator (threshold map, noise).
        camera: defaults to :meth:`Camera.default` (640x480, f = 502.3).
        C, sigma_C, refractory_us, noise_rate_hz: :class:`torchevtrack.synth.esim.ESIM` parameters.
        background: grey level of the static background, in ``[0, 1]``.
        max_px_per_frame: largest image motion between two rendered frames, pixels.
        gt_rate_hz: ground-truth pose rate (must divide 1e6 / 100 us samples evenly).
        render_faces: render a decimated copy with about this many faces (the saved mesh and the
            poses stay those of the full mesh); ``None`` renders the full mesh.
        progress: show a tqdm bar over frames.

    Returns:
        The :class:`Sequence` (events, camera, ground truth at ``gt_rate_hz``, full mesh, metadata).
    """
    camera = Camera.default() if camera is None else camera
    if not 0.0 <= background <= 1.0:
        raise ValueError(f"background must be a grey level in [0, 1], got {background}")
    dt_us = 100
    if gt_rate_hz <= 0 or (1_000_000 // gt_rate_hz) % dt_us or 1_000_000 % gt_rate_hz:
        raise ValueError(f"gt_rate_hz must divide 10 kHz evenly (e.g. 500, 1000), got {gt_rate_hz}")
    mesh = load_mesh(object_name)
    render_mesh = mesh if render_faces is None else load_mesh(object_name, decimate=render_faces)
    t_us, poses = make_trajectory(motion, duration_s, seed, camera, mesh, dt_us=dt_us)
    corners = bbox_corners(mesh)
    frames = frame_times(t_us, poses, camera, corners, max_px_per_frame)
    boxes = projected_bbox(poses[frames], camera, corners)

    sim = ESIM(camera.height, camera.width, C=C, sigma_C=sigma_C, refractory_us=refractory_us,
               noise_rate_hz=noise_rate_hz, seed=seed)
    chunks: list[EventStream] = []
    # One torch thread: the per-frame tensors are small, and torch's worker threads fighting the software
    # rasteriser's threads made generation 2x slower (measured). Restored on exit.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with Renderer(render_mesh, camera, background=background) as renderer:
            sim(renderer.render(poses[frames[0]]).gray[0], int(t_us[frames[0]]))
            bar = tqdm(range(1, len(frames)), desc=f"{object_name} {motion}", unit="frame", disable=not progress)
            for j in bar:
                roi = roi_union(boxes[j - 1: j + 1], camera)
                gray = renderer.render(poses[frames[j]], roi=roi).gray[0]
                chunks.append(sim(gray, int(t_us[frames[j]]), roi=roi))
    finally:
        torch.set_num_threads(threads)
    events = EventStream.concat(chunks)

    step = 1_000_000 // gt_rate_hz
    gt_t = torch.arange(0, int(t_us[-1]) + 1, step, dtype=torch.int64)
    gt_poses = interpolate_poses(t_us, poses, gt_t)
    stats = motion_stats(gt_t, gt_poses, camera)
    meta = {
        "object": object_name,
        "motion": motion,
        "seed": int(seed),
        "duration_s": float(duration_s),
        "n_events": len(events),
        "events_per_s": len(events) / float(duration_s),
        "speeds": stats,
        "depth_range_m": [float(gt_poses[:, 2].min()), float(gt_poses[:, 2].max())],
        "generator": {
            "esim": {"C": C, "sigma_C": sigma_C, "refractory_us": refractory_us, "noise_rate_hz": noise_rate_hz,
                     "log_eps": 1e-3},
            "background": background,
            "max_px_per_frame": max_px_per_frame,
            "n_frames": len(frames),
            "trajectory_dt_us": dt_us,
            "gt_rate_hz": gt_rate_hz,
            "mesh_faces": len(mesh.faces),
            "render_faces": len(render_mesh.faces),
        },
        "torchevtrack_version": torchevtrack.__version__,
    }
    return Sequence(events, camera, gt_t, gt_poses, mesh, meta)
