"""Synthetic event sequences: trajectory -> shaded renders -> ESIM events, with ground truth.

Pipeline of :func:`generate_sequence`:

1. A seeded trajectory (:func:`torchevtrack.synth.trajectory.make_trajectory`), sampled every 100 us.
2. Frame times chosen adaptively: a new frame once the projected mesh bounding-box corners have moved
   ``max_px_per_frame`` pixels (summed over the dense samples, max over corners) since the last one.
3. Each frame renders only the region of interest (the union of the projected boxes at the previous
   and the current pose, plus 3 px) in front of a static uniform grey background; the ESIM updates
   that window only (every other pixel is unchanged, so it cannot emit).
4. Ground truth at ``gt_rate_hz`` (500 Hz) from the same trajectory.

Options that widen the world (each recorded in ``meta.json`` when used): sensor noise, hot pixels and a
refractory period (:class:`~torchevtrack.synth.esim.ESIM`), a hand holding the object
(:mod:`torchevtrack.synth.hand`; rendered with the object into the same frames, so it makes events and hides
part of the silhouette; the saved mesh and poses stay the object's), a printed texture on the object
(:func:`torchevtrack.synth.texture.printed_texture`), the depth range and the render backend.

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
import trimesh
from tqdm import tqdm

import torchevtrack
from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.geometry import interpolate_poses, transform_points
from torchevtrack.mesh import load_mesh
from torchevtrack.render import make_renderer
from torchevtrack.synth.esim import ESIM
from torchevtrack.synth.hand import Hand, make_hand, with_hand
from torchevtrack.synth.sequence import Sequence
from torchevtrack.synth.trajectory import (bbox_corners, leave_and_return, make_trajectory, motion_stats,
                                          projected_bbox)

__all__ = ["OCCLUDERS", "TEXTURES", "frame_times", "roi_union", "generate_sequence", "occluded_fraction"]

_ROI_MARGIN = 3
OCCLUDERS = ("none", "hand")
TEXTURES = ("none", "random")
_ZNEAR = 0.01
_OCCLUSION_SAMPLES = 24


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
    plus ``margin`` pixels, clipped to the sensor; ``(0, 0, 1, 1)`` (one pixel of background) where the boxes lie
    outside it (an object out of view: nothing of it to render)."""
    u0 = max(int(math.floor(float(boxes[:, 0].min()))) - margin, 0)
    v0 = max(int(math.floor(float(boxes[:, 1].min()))) - margin, 0)
    u1 = min(int(math.ceil(float(boxes[:, 2].max()))) + margin, camera.width - 1)
    v1 = min(int(math.ceil(float(boxes[:, 3].max()))) + margin, camera.height - 1)
    if u1 < u0 or v1 < v0:
        return 0, 0, 1, 1
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
    hot_pixels: int = 0,
    hot_pixel_rate_hz: float = 100.0,
    occluder: str = "none",
    texture: str = "none",
    depth_range: tuple[float, float] = (0.3, 0.7),
    background: float = 0.2,
    max_px_per_frame: float = 0.5,
    gt_rate_hz: int = 500,
    render_faces: int | None = None,
    render_backend: str = "pyrender",
    leave_view: tuple[float, float] | None = None,
    progress: bool = True,
) -> Sequence:
    """Simulate one sequence.

    Args:
        object_name: mesh name or path for :func:`torchevtrack.mesh.load_mesh`.
        motion: a motion group of :data:`torchevtrack.synth.trajectory.MOTION_GROUPS` (``"regular"``,
            ``"fast"``, ``"turn"``, ``"mixed"``).
        duration_s: seconds.
        seed: seeds the trajectory, the simulator (threshold map, hot pixels, noise) and the texture.
        camera: defaults to :meth:`Camera.default` (640x480, f = 502.3).
        C, sigma_C, refractory_us, noise_rate_hz, hot_pixels, hot_pixel_rate_hz:
            :class:`torchevtrack.synth.esim.ESIM` parameters (the refractory period applies to every event).
        occluder: ``"none"`` or ``"hand"`` (:mod:`torchevtrack.synth.hand`).
        texture: ``"none"`` or ``"random"``: a printed texture (seeded by ``seed``) on the rendered object; the
            sequence's ``mesh`` stays untextured (a CAD model's geometry) and its ``textured_mesh`` is the printed
            object (``printed_texture(load_mesh(object_name), seed)``, a textured scan's model).
        depth_range: ``(min, max)`` object distance, metres (raised for objects too large to fit).
        background: grey level of the static background, in ``[0, 1]``.
        max_px_per_frame: largest image motion between two rendered frames, pixels.
        gt_rate_hz: ground-truth pose rate (must divide 1e6 / 100 us samples evenly).
        render_faces: render a decimated copy with about this many faces (the saved mesh and the
            poses stay those of the full mesh); ``None`` renders the full mesh.
        render_backend: ``"pyrender"`` or ``"raster"`` (:func:`torchevtrack.render.make_renderer`; the same
            images up to rasterisation ties, the compiled raster several times faster).
        leave_view: ``(start_s, away_s)``: the object slides out of the view from ``start_s``, stays out for
            ``away_s`` seconds and slides back (:func:`~torchevtrack.synth.trajectory.leave_and_return`); ``None``:
            it stays in view throughout.
        progress: show a tqdm bar over frames.

    Returns:
        The :class:`Sequence` (events, camera, ground truth at ``gt_rate_hz``, full mesh, metadata and, with a
        texture, the printed model).
    """
    camera = Camera.default() if camera is None else camera
    if not 0.0 <= background <= 1.0:
        raise ValueError(f"background must be a grey level in [0, 1], got {background}")
    if occluder not in OCCLUDERS:
        raise ValueError(f"occluder must be one of {OCCLUDERS}, got {occluder!r}")
    if texture not in TEXTURES:
        raise ValueError(f"texture must be one of {TEXTURES}, got {texture!r}")
    dt_us = 100
    if gt_rate_hz <= 0 or (1_000_000 // gt_rate_hz) % dt_us or 1_000_000 % gt_rate_hz:
        raise ValueError(f"gt_rate_hz must divide 10 kHz evenly (e.g. 500, 1000), got {gt_rate_hz}")
    mesh = load_mesh(object_name)
    render_mesh = mesh if render_faces is None else load_mesh(object_name, decimate=render_faces)
    textured_mesh = None
    if texture == "random":  # the tracker's mesh stays the object's geometry, as a CAD model; the print goes beside it
        from torchevtrack.synth.texture import printed_texture

        render_mesh = printed_texture(render_mesh, seed)
        textured_mesh = render_mesh if render_faces is None else printed_texture(mesh, seed)
    t_us, poses = make_trajectory(motion, duration_s, seed, camera, mesh, dt_us=dt_us, depth_range=depth_range)
    if leave_view is not None:
        poses = leave_and_return(t_us, poses, camera, mesh, *leave_view)
    hand = make_hand(mesh) if occluder == "hand" else None
    # Frames follow the object and the hand's grip; the forearm (long, leaving the image) only widens the windows.
    corners = bbox_corners(mesh if hand is None else trimesh.util.concatenate([mesh, hand.grip]))
    frames = frame_times(t_us, poses, camera, corners, max_px_per_frame)
    boxes = projected_bbox(poses[frames], camera, corners)
    if hand is not None:
        boxes = _union_boxes(boxes, _forearm_boxes(poses[frames], camera, hand))
        scene_mesh = with_hand(render_mesh, hand)
    else:
        scene_mesh = render_mesh

    sim = ESIM(camera.height, camera.width, C=C, sigma_C=sigma_C, refractory_us=refractory_us,
               noise_rate_hz=noise_rate_hz, seed=seed, hot_pixels=hot_pixels, hot_pixel_rate_hz=hot_pixel_rate_hz)
    chunks: list[EventStream] = []
    # One torch thread: the per-frame tensors are small, and torch's worker threads fighting the software
    # rasteriser's threads made generation 2x slower (measured). Restored on exit.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with make_renderer(scene_mesh, camera, render_backend, znear=_ZNEAR, background=background) as renderer:
            sim(renderer.render(poses[frames[0]]).gray[0], int(t_us[frames[0]]))
            bar = tqdm(range(1, len(frames)), desc=f"{object_name} {motion}", unit="frame", disable=not progress)
            for j in bar:
                roi = roi_union(boxes[j - 1: j + 1], camera)
                gray = renderer.render(poses[frames[j]], roi=roi).gray[0]
                chunks.append(sim(gray, int(t_us[frames[j]]), roi=roi))
        occlusion = None
        if hand is not None:
            sample = poses[torch.linspace(0, len(poses) - 1, _OCCLUSION_SAMPLES).round().long()]
            occlusion = occluded_fraction(render_mesh, scene_mesh, camera, sample, render_backend)
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
    # The effects beyond the standard benchmark's, recorded only when used (a standard sequence's meta.json
    # stays as it was).
    if hot_pixels:
        meta["generator"]["esim"].update(hot_pixels=int(hot_pixels), hot_pixel_rate_hz=float(hot_pixel_rate_hz))
        meta["hot_pixels"] = sim.hot_pixel_coords()
    if hand is not None:
        meta["occluder"] = {"kind": "hand", "occluded_fraction": occlusion,
                            "forearm_segment_m": hand.forearm_segment.tolist(), "forearm_radius_m": hand.forearm_radius}
    if texture != "none":
        meta["texture"] = {"kind": texture, "seed": int(seed)}
    if tuple(depth_range) != (0.3, 0.7):
        meta["generator"]["depth_range_m"] = [float(v) for v in depth_range]
    if render_backend != "pyrender":
        meta["generator"]["render_backend"] = render_backend
    if leave_view is not None:
        meta["leave_view"] = {"start_s": float(leave_view[0]), "away_s": float(leave_view[1])}
    return Sequence(events, camera, gt_t, gt_poses, mesh, meta, textured_mesh)


def occluded_fraction(obj: trimesh.Trimesh, scene: trimesh.Trimesh, camera: Camera, poses: torch.Tensor,
                      backend: str = "pyrender") -> dict:
    """How much of the object's silhouette the rest of ``scene`` (a hand) hides, at each of ``poses``.

    A pixel of the object's own silhouette (depth render of ``obj``) is hidden when the scene's depth there is
    nearer than the object's by more than 0.1 mm. Returns ``{"mean", "median", "min", "max"}`` of the per-pose
    fraction of hidden silhouette pixels (poses with the object out of view are skipped).
    Shape: ``poses (K, 7)``.
    """
    with make_renderer(obj, camera, backend, znear=_ZNEAR) as r_obj, \
            make_renderer(scene, camera, backend, znear=_ZNEAR) as r_all:
        d_obj = r_obj.render(poses, shaded=False).depth
        d_all = r_all.render(poses, shaded=False).depth
    seen = d_obj > 0
    hidden = seen & (d_all < d_obj - 1e-4)
    area = seen.flatten(1).sum(1)
    frac = (hidden.flatten(1).sum(1) / area.clamp_min(1))[area > 0].double()
    if frac.numel() == 0:
        raise ValueError("the object is never in view")
    return {"mean": float(frac.mean()), "median": float(frac.median()), "min": float(frac.min()),
            "max": float(frac.max())}


def _forearm_boxes(poses: torch.Tensor, camera: Camera, hand: Hand, samples: int = 64) -> torch.Tensor:
    """Image boxes ``(N, 4)`` of the forearm at ``poses`` (N, 7): points along its axis in front of the camera,
    each padded by the projected radius (points behind the camera are skipped; an all-hidden forearm gives
    an empty box that does not widen a union)."""
    s = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)[:, None]
    seg = torch.as_tensor(hand.forearm_segment, dtype=torch.float64)
    axis = seg[0] + s * (seg[1] - seg[0])
    pc = transform_points(poses.to(torch.float64), axis)  # (N, S, 3)
    z = pc[..., 2]
    front = z > 2.0 * _ZNEAR
    uv = camera.project(torch.where(front[..., None], pc, torch.ones_like(pc)))
    pad = hand.forearm_radius * max(camera.fx, camera.fy) / z.clamp_min(2.0 * _ZNEAR) + 1.0
    big = torch.tensor(float("inf"), dtype=torch.float64)
    lo = torch.where(front[..., None], uv - pad[..., None], big).amin(1)
    hi = torch.where(front[..., None], uv + pad[..., None], -big).amax(1)
    return torch.cat((lo, hi), dim=-1)


def _union_boxes(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per row the box holding both ``[u_min, v_min, u_max, v_max]`` boxes. Shape: ``(N, 4), (N, 4) -> (N, 4)``."""
    return torch.cat((torch.minimum(a[:, :2], b[:, :2]), torch.maximum(a[:, 2:], b[:, 2:])), dim=-1)
