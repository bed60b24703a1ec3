"""Re-localisation: a wide, coarse-to-fine search for the object's pose against the recent events.

When the tracker has lost the object (the loss detector, :mod:`torchevtrack.loss`), the local template search
cannot reach it: it moves a few pixels / half degrees per update. :class:`Relocaliser` searches a neighbourhood of
a pose (the last good one, extrapolated) of about +-10 cm and +-45 deg with the two-sided chamfer cost between the
recent events and the rendered model's edges (:mod:`torchevtrack.chamfer`).

1. **Observation**, once per call: the pixels of the time surface that fired within a window before ``t_now``
   and have a recent neighbour (:func:`~torchevtrack.chamfer.recent_events`). The window adapts to the motion: the
   shortest one (between ``min_window_us`` and ``max_window_us``) whose event pixels in the search region number
   ``events_per_edge`` times the model's silhouette edge pixels at the start pose (4 by default: with one, 48 ms
   after a start the few events cover part of the outline and the cost's minimum can sit 7 cm deeper than the
   truth, cheaper than it; docs/notebook.md, 2026-12-07 morning).
2. **Levels** (coarse to fine, :data:`LEVELS`). At each level every combination of a rotation offset
   ``{-a, 0, a}`` about each camera axis (through the object origin, applied on the left as everywhere) and a
   depth offset from the level's list is rendered around the current centre, at the level's image ``scale``, in
   one square region that holds every candidate and its image-plane shifts. The image-plane translation is not
   enumerated: the chamfer cost of every shift within the level's radius comes from two FFT correlations (model
   edges with the observation's distance map, the model's distance map with the event image), so a candidate
   costs one low-resolution render, one distance transform and two small FFTs. The best shift becomes the
   candidate's ``x, y`` (``dx = shift_px z / fx``). The ``beam`` best pairwise-distinct first-level candidates
   are each refined through the next levels (each level's best is the next one's centre) and polished (3.); while
   none of them reaches ``seed_cost_px``, the next-best distinct candidates are, up to ``max_seeds`` in all.
3. **Polish** at full resolution: damped Gauss-Newton on the distances of the model's edge pixels to the nearest
   recent event (their image Jacobian through the interaction matrix, depth from the render), a fresh render per
   step, a step kept only when the two-sided cost falls (``polish_steps`` steps). The best polished seed is
   polished again from six starts turned by +-``kick_deg`` about each axis (out of a nearby local minimum).
4. **Clear winner.** The result is the refined seed of lowest full-resolution cost; ``runner_up`` is the lowest
   cost of the other refined seeds that ended distinct from it (farther than ``distinct_m`` / ``distinct_deg``;
   ``inf`` if none did). The result is ``clear`` when its cost is at most ``max_cost_px`` and the runner-up costs
   at least ``min_margin_px`` more. The result also carries the same cost of the caller's own pose (``own_cost``;
   by default the search's centre), for a caller with a pose of its own to compare with (the tracker's:
   :func:`~torchevtrack.recover.beats`).

:meth:`Relocaliser.scan` runs the first level alone over the whole frame (the candidates placed at its centre, the
shift radius the frame's half-size), for an object that is back in view far from where it was lost; a search centred
on its result then refines and judges it.

Costs are in full-resolution pixels (lower is better). Batch elements are searched one after the other; within a
search, ``workers`` threads share the first level's (and the frame scan's) candidates, refine seeds and polish the
restarts side by side, with the result of one thread (a 640x480 search on ``mustard_fast``: 0.93-0.98 s -> 0.71-0.84
s on 2 cores). The renderer may hold a decimated mesh (:func:`~torchevtrack.mesh.load_mesh` ``decimate``): the
renders dominate the cost. ``tools/bench_relocalise.py`` measures success rates and the cost of a call,
``tools/chamfer_table.py`` compares the chamfer cost with the template score at fixed offsets from the truth.

Status (measured with one event per edge, ``tools/bench_relocalise.py``; sugar box fast with and without noise,
gelatin box fast, mustard bottle fast, 2-s sequences x 3 times x 4 random starts): within 1 cm / 5 deg from 5 cm / 20
deg starts in 42 of 48, from 2 cm / 10 deg starts in 44 of 48. Every miss is the sugar box, 0.5-1.1 cm / 8-12 deg off,
and ``clear``: there the cost of the miss is within 0.2 px of the truth's; gross misses (3.5 cm / 16 deg, seen before
the restarts) end above ``max_cost_px``. A call costs about 1.0-1.5 s at 640x480 with a 16k-face mesh (renders a
third, FFTs and distance transforms a fifth each); a mesh decimated to 2000 faces halves that but found 29 of 47 from
2 cm / 10 deg (before the restarts; the full mesh then found 41 of 48).
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
import scipy.fft as sfft
import torch
from torch import nn

from torchevtrack.camera import Camera, interaction_matrix
from torchevtrack.chamfer import distance_map, model_edges, newest, recent_events
from torchevtrack.geometry import quat_rotate
from torchevtrack.raster import RasterRenderer
from torchevtrack.schedule import thread_count
from torchevtrack.stages.template import apply_steps, pose_delta, render_window

__all__ = ["LEVELS", "Level", "MAX_REGION_PX", "RIVAL_DEPTHS", "RIVAL_SCALE", "RIVAL_XY_M", "Relocalisation",
           "Relocaliser"]


class Level(NamedTuple):
    """One level of the search: rotation offset ``rot_deg`` (``{-a, 0, a}`` per axis), depth offsets ``dz_m``,
    image-plane search radius ``xy_m`` (metres at the centre's depth) and the image ``scale`` (renders and
    observation resized by it; 1 = full resolution)."""

    rot_deg: float
    dz_m: tuple[float, ...]
    xy_m: float
    scale: float


LEVELS = (
    Level(30.0, (-0.08, -0.04, 0.0, 0.04, 0.08), 0.10, 0.25),
    Level(15.0, (-0.02, 0.0, 0.02), 0.03, 0.25),
)
# a level's square search region is at most this many low-resolution pixels across: its scale shrinks below the
# level's where the square would be larger (an estimate drifted near the camera, or a frame scan at 1280x720; the
# regions of the wide dev split's and the standard eight's true poses are at most 303 px, their frame scans 540 px).
# Unbounded, one frame scan at 1280x720 of a cracker box at 0.3 m held 10.3 GB and took 32 s, and `benchmark
# --recover` on the dev pair peaked at 17.8 GB (docs/notebook.md, 2026-12-07 late morning)
MAX_REGION_PX = 512
# Relocaliser.rivals: the depth factors of a pose's rivals, their image-plane reach (m) and the image scale
RIVAL_DEPTHS = (0.8, 1.25)
RIVAL_XY_M = 0.03
RIVAL_SCALE = 0.25


class Relocalisation(NamedTuple):
    """Result of :meth:`Relocaliser.forward`, all with a leading ``B``.

    Attributes:
        pose: ``(B, 7)`` float64 best pose found.
        cost: ``(B,)`` float64 its chamfer cost (full-resolution pixels, at the last level's scale).
        runner_up: ``(B,)`` float64 cost of the best first-level candidate distinct from ``pose``.
        clear: ``(B,)`` bool, ``cost <= max_cost_px`` and ``runner_up - cost >= min_margin_px``.
        own_cost: ``(B,)`` float64 the same cost of the caller's own pose (``own`` of :meth:`Relocaliser.forward`).
    """

    pose: torch.Tensor
    cost: torch.Tensor
    runner_up: torch.Tensor
    clear: torch.Tensor
    own_cost: torch.Tensor


class _Region(NamedTuple):
    """A level's square search region: full-resolution top-left ``u0, v0``, the low-resolution camera of its renders
    at ``scale`` (the level's, or less where the square would exceed ``MAX_REGION_PX``), the shift radius ``R`` and
    the FFT size ``N`` (low-res pixels), and the observation's Fourier transforms (event image, capped distance map)
    on the ``N x N`` canvas."""

    u0: int
    v0: int
    camera: Camera
    scale: float
    R: int
    N: int
    f_events: np.ndarray
    f_dist: np.ndarray
    n_events: int


@contextlib.contextmanager
def _threads(n: int):
    """Something with ``map(fn, items)`` (results in order): a pool of ``n`` threads, or the calling thread for 1."""
    if n == 1:
        yield SimpleNamespace(map=map)
    else:
        with ThreadPoolExecutor(n, thread_name_prefix="torchevtrack-relocalise") as pool:
            yield pool


class _FullRes(NamedTuple):
    """The observation at full resolution: event image ``(H, W)`` bool, its capped distance map ``(H, W)``
    float32 and that map's central differences along u and v ``(H, W)`` float64 (zero on the border; ``None`` for a
    cost, which needs none: the polish does), and the event pixels ``(K, 2)`` (u, v) of the first level's region."""

    image: np.ndarray
    distance: np.ndarray
    grad_u: np.ndarray | None
    grad_v: np.ndarray | None
    events: np.ndarray

    @classmethod
    def of(cls, image: np.ndarray, cap_px: float, events: np.ndarray) -> "_FullRes":
        distance = distance_map(image, cap_px)
        D = distance.astype(np.float64)
        gu, gv = np.zeros_like(D), np.zeros_like(D)
        gu[:, 1:-1] = 0.5 * (D[:, 2:] - D[:, :-2])
        gv[1:-1] = 0.5 * (D[2:] - D[:-2])
        return cls(image, distance, gu, gv, events)


class Relocaliser(nn.Module):
    """Wide coarse-to-fine pose search with the chamfer cost (module docstring). Stateless (no buffers), so one
    instance may run in a worker thread (its compiled kernels release the GIL) on a snapshot of the time surface
    (``last_us.clone()``: the search reads it throughout).

    Args:
        renderer: the object's :class:`~torchevtrack.raster.RasterRenderer` (its camera is the frame's).
        radius: the object's bounding radius (metres), for the search regions.
        levels: the search levels (default :data:`LEVELS`).
        cap_px: distances are truncated at this many full-resolution pixels.
        min_window_us, max_window_us, events_per_edge: the observation's adaptive recency window (module
            docstring, 1.).
        beam, max_seeds: first-level candidates refined always / at most.
        seed_cost_px: more candidates (up to ``max_seeds``) are refined while none has reached this cost: the more
            seeds, the likelier a wrong result meets a distinct runner-up of about its cost (default: ``max_cost_px``).
        polish_steps: Gauss-Newton steps at full resolution per refined seed.
        kick_deg: the best result is polished again from six starts turned by +-``kick_deg`` about each camera
            axis, and replaced by a lower-cost one (0: no restarts).
        max_cost_px, min_margin_px, distinct_m, distinct_deg: the clear-winner rule (and the seeds' distinctness).
        symmetry_axis: ``(3,)`` object-frame axis, through the origin, of a rotational symmetry of the object's shape
            (:func:`~torchevtrack.mesh.symmetry_axis`): poses that differ only by a turn about it are not distinct
            (else such a twin, of the same cost, keeps every result from being clear). Colours that break the
            symmetry are ignored: a result may then be turned about the axis.
        workers: threads that refine seeds and polish restarts side by side (default: the usable cores; the search
            blocks its caller meanwhile). The result is the same for any number: seeds are judged in their order.

    ``forward(pose (B, 7), last_us (B, H, W) or (B, C, H, W) int64, t_now_us (B,) int64, own (B, 7) = pose) ->
    Relocalisation``: ``last_us`` is a time surface (newest event per pixel and channel, microseconds), ``pose`` the
    centre of the search (object in the camera frame), ``own`` the caller's own pose, whose cost the result carries.

    Example:
        >>> import torch
        >>> from torchevtrack.camera import Camera, interaction_matrix
        >>> from torchevtrack.mesh import load_mesh
        >>> reloc = Relocaliser(RasterRenderer(load_mesh("box"), Camera(160, 120, 150.0, 150.0, 80.0, 60.0)), 0.1)
        >>> last = torch.full((1, 120, 160), -(2 ** 62))  # no events
        >>> out = reloc(torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]]), last, torch.tensor([1000]))
        >>> out.pose.shape, bool(out.clear[0])
        (torch.Size([1, 7]), False)
    """

    def __init__(self, renderer: RasterRenderer, radius: float, *, levels: tuple[Level, ...] = LEVELS,
                 cap_px: float = 20.0, min_window_us: int = 1000, max_window_us: int = 30000,
                 events_per_edge: float = 4.0, beam: int = 3, max_seeds: int = 6, polish_steps: int = 15,
                 kick_deg: float = 7.5,
                 max_cost_px: float = 1.5, min_margin_px: float = 0.5, seed_cost_px: float | None = None,
                 distinct_m: float = 0.02, distinct_deg: float = 15.0,
                 symmetry_axis: torch.Tensor | np.ndarray | None = None, workers: int | None = None):
        super().__init__()
        if not isinstance(renderer, RasterRenderer):
            raise TypeError(f"renderer must be a RasterRenderer, got {type(renderer).__name__}")
        if not radius > 0:
            raise ValueError(f"radius must be positive (metres), got {radius}")
        if not levels:
            raise ValueError("at least one level is needed")
        if not 0 < min_window_us <= max_window_us:
            raise ValueError(f"need 0 < min_window_us <= max_window_us, got {min_window_us}, {max_window_us}")
        self.renderer, self.camera, self.radius = renderer, renderer.camera, float(radius)
        self.levels, self.cap_px = tuple(levels), float(cap_px)
        self.min_window_us, self.max_window_us = int(min_window_us), int(max_window_us)
        self.events_per_edge = float(events_per_edge)
        self.polish_steps, self.max_cost_px = int(polish_steps), float(max_cost_px)
        self.seed_cost_px = self.max_cost_px if seed_cost_px is None else float(seed_cost_px)
        self.kick_deg = float(kick_deg)
        self.max_seeds = max(int(max_seeds), int(beam))
        self.beam, self.min_margin_px, self.distinct_m = int(beam), float(min_margin_px), float(distinct_m)
        self.distinct_rad = math.radians(distinct_deg)
        self.symmetry_axis = None if symmetry_axis is None else \
            torch.nn.functional.normalize(torch.as_tensor(symmetry_axis, dtype=torch.float64), dim=0)
        self.workers = thread_count(workers)

    @property
    def depth_reach_m(self) -> float:
        """How far in depth the levels reach from a search's centre (metres): the sum of their largest depth
        offsets."""
        return sum(max(abs(dz) for dz in lv.dz_m) for lv in self.levels)

    # -- the observation ------------------------------------------------------------------------------------------
    def _events(self, pose: torch.Tensor, last_us: torch.Tensor, t_now: int, level: Level | None = None,
                offset: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Recent event pixels ``(K, 2)`` (u, v) in ``level``'s region (default the first level's), with the adaptive
        window; ``last_us`` may be a crop of the frame's surface whose top-left pixel is ``offset`` (u, v)."""
        level = self.levels[0] if level is None else level
        u0, v0, side = self._square(pose, level)
        last = newest(last_us)
        H, W = last.shape
        cu, cv = u0 - offset[0], v0 - offset[1]  # the square in the crop
        age = t_now - last[max(0, cv):min(H, cv + side), max(0, cu):min(W, cu + side)]
        ages = age[(age >= 0) & (age <= self.max_window_us)]
        depth, _ = self.renderer.render_unit(pose.numpy(), Camera(*self._low_camera(u0, v0, side, level.scale)),
                                             shaded=False)
        edges = int(model_edges(depth[0]).sum() / level.scale)
        k = min(len(ages), max(1, round(self.events_per_edge * edges)))
        kth = np.partition(ages, k - 1)[k - 1] if k > 0 else self.max_window_us  # the k-th most recent pixel's age
        window = int(np.clip(kth, self.min_window_us, self.max_window_us))
        mask = recent_events(last, t_now, window, min_support=1)
        v, u = np.nonzero(mask)
        return np.stack((u + offset[0], v + offset[1]), 1)

    def _square(self, pose: torch.Tensor, level: Level) -> tuple[int, int, int]:
        """Full-resolution square ``(u0, v0, side)`` holding the object at every candidate depth and shift."""
        cam = self.camera
        x, y, z = (float(v) for v in pose[0, :3])
        zn = max(z + min(level.dz_m), 1.5 * self.radius)
        half = cam.fx * self.radius / (zn - self.radius) + cam.fx * level.xy_m / zn + 2
        uc, vc = cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy
        side = 2 * math.ceil(half)
        return int(math.floor(uc - half)), int(math.floor(vc - half)), side

    def _low_camera(self, u0: int, v0: int, side: int, scale: float) -> tuple:
        n = math.ceil(side * scale)
        c = self.camera
        return (n, n, c.fx * scale, c.fy * scale, (c.cx - u0 + 0.5) * scale - 0.5, (c.cy - v0 + 0.5) * scale - 0.5)

    def _region(self, pose: torch.Tensor, level: Level, events: np.ndarray) -> _Region:
        u0, v0, side = self._square(pose, level)
        scale = min(level.scale, MAX_REGION_PX / side)
        cam = Camera(*self._low_camera(u0, v0, side, scale))
        n = cam.width
        R = max(1, math.ceil(self.camera.fx * level.xy_m / float(pose[0, 2]) * scale))
        N = sfft.next_fast_len(n + R, real=True)  # >= n + R: a shift never wraps a pixel into the region
        cap = self.cap_px * scale
        ev = np.zeros((N, N), np.float32)
        iu = np.floor((events[:, 0] - u0 + 0.5) * scale).astype(np.int64)
        iv = np.floor((events[:, 1] - v0 + 0.5) * scale).astype(np.int64)
        keep = (iu >= 0) & (iu < n) & (iv >= 0) & (iv < n)
        ev[iv[keep], iu[keep]] = 1.0
        dist = np.full((N, N), cap, np.float32)
        dist[:n, :n] = distance_map(ev[:n, :n] > 0, cap)
        return _Region(u0, v0, cam, scale, R, N, sfft.rfft2(ev), sfft.rfft2(dist), int(ev.sum()))

    # -- candidates -----------------------------------------------------------------------------------------------
    def _search(self, poses: torch.Tensor, region: _Region, pool=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Best shift of each candidate ``(K, 7)``: shifted poses ``(K, 7)`` and their costs ``(K,)`` (full-res
        pixels; ``cap_px`` for a candidate not seen). With a ``pool`` (:func:`_threads`), its threads take a share of
        the candidates each (every candidate's cost is its own: the same result)."""
        if pool is not None and self.workers > 1 and len(poses) > 1:
            parts = poses.tensor_split(min(self.workers, len(poses)))
            shares = pool.map(lambda part: self._search(part, region), parts)
            found, costs = zip(*shares)
            return torch.cat(found), torch.cat(costs)
        depth, gray = self.renderer.render_unit(poses.numpy(), region.camera, shaded=True)
        edges = model_edges(depth, gray)
        K, n, R, N, s = len(poses), region.camera.width, region.R, region.N, region.scale
        cap = self.cap_px * s
        E = np.zeros((K, N, N), np.float32)
        E[:, :n, :n] = edges
        D = np.full((K, N, N), cap, np.float32)
        D[:, :n, :n] = distance_map(edges, cap)
        m = edges.sum((1, 2))
        # per shift (dv, du): model edges -> events (a) and events -> model edges (b), both correlations
        a = sfft.irfft2(sfft.rfft2(E).conj() * region.f_dist, s=(N, N)) / np.maximum(m, 1)[:, None, None]
        b = sfft.irfft2(sfft.rfft2(D).conj() * region.f_events, s=(N, N)) / max(region.n_events, 1)
        idx = np.arange(-R, R + 1) % N
        c = (0.5 * (a + b))[:, idx][:, :, idx].reshape(K, -1)
        j = c.argmin(1)
        cost = c[np.arange(K), j] / s
        cost[(m == 0) | (region.n_events == 0)] = self.cap_px
        dv, du = j // (2 * R + 1) - R, j % (2 * R + 1) - R
        out = poses.clone()
        out[:, 0] += torch.from_numpy(du / s / self.camera.fx) * poses[:, 2]
        out[:, 1] += torch.from_numpy(dv / s / self.camera.fy) * poses[:, 2]
        return out, torch.from_numpy(cost.astype(np.float64))

    def _candidates(self, centre: torch.Tensor, level: Level) -> torch.Tensor:
        a = math.radians(level.rot_deg)
        steps = torch.tensor([[0.0, 0.0, dz, rx, ry, rz] for dz in level.dz_m
                              for rx, ry, rz in itertools.product((-a, 0.0, a), repeat=3)], dtype=torch.float64)
        poses = apply_steps(centre, steps[None])[0]
        return poses[poses[:, 2] > 1.5 * self.radius]

    def _distinct(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Whether each pose of ``b`` ``(K, 7)`` is farther than the distinct rule from ``a`` ``(1, 7)``: ``(K,)``."""
        d = pose_delta(a, b[None])[0]
        rot = d[:, 3:]
        if self.symmetry_axis is not None:  # a turn about the symmetry axis (camera frame at a) changes no edge
            n = quat_rotate(a[0, 3:], self.symmetry_axis)
            rot = rot - (rot @ n)[:, None] * n
        return (d[:, :3].norm(dim=1) > self.distinct_m) | (rot.norm(dim=1) > self.distinct_rad)

    def _one(self, pose: torch.Tensor, own: torch.Tensor, last_us: torch.Tensor, t_now: int,
             pool) -> tuple[torch.Tensor, float, float, float]:
        """The search of one element (module docstring), its threads' work on ``pool`` (:func:`_threads`)."""
        centre = pose.double()
        events = self._events(centre, last_us, t_now)
        first = self.levels[0]
        poses, costs = self._search(self._candidates(centre, first), self._region(centre, first, events), pool)
        seeds = []  # the best first-level candidates, pairwise distinct
        for j in costs.argsort().tolist():
            if len(seeds) == self.max_seeds:
                break
            if all(bool(self._distinct(seed, poses[j:j + 1])[0]) for seed in seeds):
                seeds.append(poses[j:j + 1])
        obs = self._full_res(events)

        def refine(seed: torch.Tensor) -> tuple[float, torch.Tensor]:  # through the next levels, then polished
            for level in self.levels[1:]:
                p, c = self._search(self._candidates(seed, level), self._region(seed, level, events))
                seed = p[int(c.argmin()):int(c.argmin()) + 1]
            return self._polish(seed, obs)

        finals = list(pool.map(refine, seeds[:self.beam]))
        rest = seeds[self.beam:]
        # more seeds while none has reached a low cost: `workers` at a time, those past the stop dropped (the result
        # as if refined one by one)
        while rest and min(c for c, _ in finals) > self.seed_cost_px:
            for done in pool.map(refine, rest[:self.workers]):
                if min(c for c, _ in finals) <= self.seed_cost_px:
                    break
                finals.append(done)
            rest = rest[self.workers:]
        finals.sort(key=lambda cp: cp[0])
        cost, best = finals[0]
        if self.kick_deg > 0:  # restarts turned by +-kick about each axis: out of a nearby local minimum
            k = math.radians(self.kick_deg)
            kicks = torch.tensor([[0, 0, 0] + [sg * k if i == ax else 0.0 for i in range(3)]
                                  for ax in range(3) for sg in (-1, 1)], dtype=torch.float64)
            for c, p in pool.map(lambda start: self._polish(start[None], obs), apply_steps(best, kicks[None])[0]):
                if c < cost:
                    cost, best = c, p
        others = [c for c, p in finals[1:] if bool(self._distinct(best, p)[0])]
        return best[0], cost, min(others, default=math.inf), self._cost_of(self._edges_full(own.double()), obs)

    # -- full resolution: cost and Gauss-Newton polish -------------------------------------------------------------
    def _full_res(self, events: np.ndarray, box: tuple[int, int, int, int] | None = None) -> "_FullRes":
        """The observation of the event pixels ``(K, 2)``; with ``box`` ``(u0, v0, u1, v1)`` (full-resolution pixels,
        clipped to the frame), for costs only: its distances only there, ``cap_px`` elsewhere, and no gradients."""
        frame = np.zeros((self.camera.height, self.camera.width), bool)
        frame[events[:, 1], events[:, 0]] = True
        if box is None:
            return _FullRes.of(frame, self.cap_px, events)
        H, W = frame.shape
        u0, v0, u1, v1 = max(box[0], 0), max(box[1], 0), min(box[2], W), min(box[3], H)
        distance = np.full((H, W), self.cap_px, np.float32)
        if u1 > u0 and v1 > v0:
            distance[v0:v1, u0:u1] = distance_map(frame[v0:v1, u0:u1], self.cap_px)
        return _FullRes(frame, distance, None, None, events)

    def _edges_full(self, pose: torch.Tensor):
        """Edge pixels ``(M, 2)`` (frame u, v), their depths ``(M,)`` and the render window, or ``None``."""
        if not float(pose[0, 2]) > 1.5 * self.radius:
            return None
        u0, v0, w, h = (int(x) for x in render_window(pose, self.camera, self.radius, margin_px=4)[0])
        depth, gray = self.renderer.render_unit(pose.numpy(), self.camera.crop(u0, v0, w, h), shaded=True)
        e = model_edges(depth, gray)[0]
        v, u = np.nonzero(e)
        if len(u) == 0:
            return None
        return np.stack((u + u0, v + v0), 1), depth[0][v, u].astype(np.float64), (u0, v0, w, h)

    def _cost_of(self, got, obs: "_FullRes") -> float:
        """Two-sided chamfer cost at full resolution of a pose whose :meth:`_edges_full` are ``got``; the events:
        those of the first level's region."""
        if got is None or len(obs.events) == 0:
            return self.cap_px
        uv, _, (u0, v0, w, h) = got
        H, W = obs.distance.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        a = np.full(len(uv), self.cap_px)
        a[inside] = obs.distance[uv[inside, 1], uv[inside, 0]]
        c = math.ceil(self.cap_px)
        ou, ov = u0 - c, v0 - c  # the window grown by the cap: events outside it are cap away from every edge
        img = np.zeros((h + 2 * c, w + 2 * c), bool)
        img[uv[:, 1] - ov, uv[:, 0] - ou] = True
        dm = distance_map(img, self.cap_px)
        eu, ev = obs.events[:, 0] - ou, obs.events[:, 1] - ov
        near = (eu >= 0) & (eu < img.shape[1]) & (ev >= 0) & (ev < img.shape[0])
        b = (dm[ev[near], eu[near]].sum() + self.cap_px * (~near).sum()) / len(obs.events)
        return float(0.5 * (a.mean() + b))

    def _polish(self, pose: torch.Tensor, obs: "_FullRes") -> tuple[float, torch.Tensor]:
        """Damped Gauss-Newton on the model edges' distances to the events (full resolution, a fresh render per
        step, a step kept only if the two-sided cost falls; at most ``polish_steps``, fewer once converged or after
        three rejected steps in a row): ``(cost, pose)``. Each step renders once: the edges of the pose it starts from
        are those its cost was taken with."""
        got = self._edges_full(pose)
        cost = self._cost_of(got, obs)
        gu, gv = obs.grad_u, obs.grad_v
        H, W = obs.distance.shape
        cam = self.camera
        lam = 1e-3
        for _ in range(self.polish_steps):
            if got is None:
                break
            uv, z, _ = got
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
            uv, z = uv[ok], z[ok]
            r = obs.distance[uv[:, 1], uv[:, 0]].astype(np.float64)
            inl = r < 0.5 * self.cap_px  # edges far from every event do not pull
            if inl.sum() < 12:
                break
            uv, z, r = uv[inl], z[inl], r[inl]
            g = np.stack((gu[uv[:, 1], uv[:, 0]], gv[uv[:, 1], uv[:, 0]]), 1)
            L = interaction_matrix(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(z), cam.fx, cam.fy,
                                   cam.cx, cam.cy).numpy()  # (M, 2, 6) for the twist [v, w] about the camera
            t = pose[0, :3].numpy()
            M = np.eye(6)  # step [dt, phi] about the object origin -> twist: v = dt + t x phi
            M[:3, 3:] = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            J = np.einsum("mk,mkj->mj", g, L) @ M
            A = J.T @ J
            A += lam * np.diag(np.diag(A)) + 1e-9 * np.eye(6)
            step = -np.linalg.solve(A, J.T @ r)
            trial = apply_steps(pose, torch.from_numpy(step)[None, None])[0]
            got_trial = self._edges_full(trial)
            c = self._cost_of(got_trial, obs)
            if c < cost:
                pose, cost, got, lam = trial, c, got_trial, max(lam / 3, 1e-4)
                if np.abs(step).max() < 1e-4:  # converged: 0.1 mm and 0.006 deg
                    break
            elif lam > 1.0:  # three rejected steps in a row
                break
            else:
                lam *= 10
        return cost, pose

    def scan(self, pose: torch.Tensor, last_us: torch.Tensor, t_now_us: int) -> tuple[torch.Tensor, float]:
        """Where in the whole frame the object is, at about ``pose``'s depth and rotation: the first level's candidates
        (its rotations and depth offsets) placed at the frame's centre, each at its best image-plane shift over the
        whole frame (the FFT correlations of step 2, module docstring), against the recent events of the whole frame.
        For an object that left the view, or moved far during a blackout, and came back elsewhere: a search centred
        on its last pose reaches only ``levels[0].xy_m`` around it. The result is coarse (the first level's scale and
        steps); :meth:`forward` centred on it refines and judges it.

        Args:
            pose: ``(1, 7)`` the pose whose depth and rotation are tried (its position is ignored).
            last_us: ``(H, W)`` or ``(C, H, W)`` int64 time surface (us).
            t_now_us: the search's time (us).

        Returns:
            The best candidate ``(1, 7)`` float64 and its cost (full-resolution pixels at the first level's scale,
            over the whole frame's recent events: not comparable with :meth:`forward`'s costs).

        Example:
            >>> import torch
            >>> from torchevtrack.camera import Camera
            >>> from torchevtrack.mesh import load_mesh
            >>> reloc = Relocaliser(RasterRenderer(load_mesh("box"), Camera(160, 120, 150.0, 150.0, 80.0, 60.0)), 0.1)
            >>> last = torch.full((120, 160), -(2 ** 62))  # no events: a candidate, at the cap
            >>> found, cost = reloc.scan(torch.tensor([[0.3, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]]), last, 1000)
            >>> tuple(found.shape), cost
            ((1, 7), 20.0)
        """
        pose = torch.as_tensor(pose, dtype=torch.float64)
        if pose.shape != (1, 7) or last_us.ndim not in (2, 3) or last_us.dtype != torch.int64 \
                or tuple(last_us.shape[-2:]) != (self.camera.height, self.camera.width):
            raise ValueError(f"expected pose (1, 7) and last_us (H, W) or (C, H, W) int64 of the camera's "
                             f"{self.camera.height}x{self.camera.width}, got {tuple(pose.shape)}, "
                             f"{tuple(last_us.shape)} {last_us.dtype}")
        cam = self.camera
        centre = pose.clone()
        z = max(float(centre[0, 2]), 1.5 * self.radius - min(self.levels[0].dz_m) + 1e-6)
        centre[0, :3] = torch.tensor([((cam.width - 1) / 2 - cam.cx) * z / cam.fx,
                                      ((cam.height - 1) / 2 - cam.cy) * z / cam.fy, z], dtype=torch.float64)
        level = self.levels[0]._replace(xy_m=0.5 * z * max(cam.width / cam.fx, cam.height / cam.fy))
        events = self._events(centre, last_us, int(t_now_us), level)
        with _threads(self.workers) as pool:
            poses, costs = self._search(self._candidates(centre, level), self._region(centre, level, events), pool)
        j = int(costs.argmin())
        return poses[j:j + 1], float(costs[j])

    def rivals(self, pose: torch.Tensor, last_us: torch.Tensor, t_now_us: int,
               depths: Sequence[float] = RIVAL_DEPTHS) -> torch.Tensor:
        """Coarse chamfer costs of ``pose`` and of its depth rivals: the pose with its position scaled by each of
        ``depths`` (along its line of sight: the same image centre, the object nearer or farther), each at
        its best image-plane shift within ``RIVAL_XY_M`` (at its depth), at ``RIVAL_SCALE`` of the image, against the
        search's observation (module docstring, 1.) of the region around ``pose``. A rival that costs clearly less
        says the pose has drifted in depth (:class:`~torchevtrack.recover.Recoverer`'s check).

        Shape: ``(1, 7)`` pose, ``(H, W)`` or ``(C, H, W)`` int64 ``last_us`` -> ``(1 + len(depths),)`` float64
        (full-resolution pixels; ``cap_px`` for a pose with no edge or no event in view).

        Example (events on a box's outline; the pose 25 % too far, whose rival x 0.8 is the truth):
            >>> import torch
            >>> from torchevtrack.camera import Camera
            >>> from torchevtrack.mesh import load_mesh
            >>> renderer = RasterRenderer(load_mesh("box"), Camera(160, 120, 150.0, 150.0, 80.0, 60.0))
            >>> truth = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]])
            >>> box = renderer.render(truth).depth[0] > 0
            >>> last = torch.where((box ^ box.roll(1, 0)) | (box ^ box.roll(1, 1)), 1000, -(2 ** 62))
            >>> far = torch.cat((truth[:, :3] * 1.25, truth[:, 3:]), 1)
            >>> cost = Relocaliser(renderer, 0.1).rivals(far, last, 1000)
            >>> int(cost.argmin()), bool(cost[1] < cost[0] - 1.0)
            (1, True)
        """
        pose = torch.as_tensor(pose, dtype=torch.float64)
        z = float(pose[0, 2])
        level = Level(0.0, (z * (min(depths) - 1),), RIVAL_XY_M, RIVAL_SCALE)
        u0, v0, side = self._square(pose, level)
        H, W = self.camera.height, self.camera.width
        a, b = max(0, v0 - 1), max(0, u0 - 1)  # the square and a pixel around it (the events' neighbours)
        # the channels' newest time taken in the crop only, not over the frame
        crop = newest(torch.as_tensor(last_us)[..., a:min(H, v0 + side + 1), b:min(W, u0 + side + 1)])
        events = self._events(pose, torch.from_numpy(np.ascontiguousarray(crop)), int(t_now_us), level,
                              offset=(b, a))
        poses = torch.cat([pose] + [torch.cat((pose[:, :3] * f, pose[:, 3:]), 1) for f in depths])
        return self._search(poses, self._region(pose, level, events))[1]

    def costs(self, poses: torch.Tensor, last_us: torch.Tensor, t_now_us: int) -> torch.Tensor:
        """The two-sided chamfer cost of each of ``poses`` against one observation of the recent events, for comparing
        poses of one object at one instant (a cost's level varies far more between scenes than between a right and
        a wrong pose of one scene: :mod:`torchevtrack.hypotheses`).

        The observation is the search's (module docstring, 1.), centred on the poses' mean position with the first
        pose's rotation: the pixels of the time surface ``last_us`` ``(H, W)`` or ``(C, H, W)`` int64 (microseconds)
        that fired within the adaptive window before ``t_now_us`` and have a recent neighbour.

        Shape: ``(K, 7) -> (K,)`` float64 full-resolution pixels (lower is better; ``cap_px`` for a pose too close to
        the camera or with no edge in view).

        Example:
            >>> import torch
            >>> from torchevtrack.camera import Camera
            >>> from torchevtrack.mesh import load_mesh
            >>> reloc = Relocaliser(RasterRenderer(load_mesh("box"), Camera(160, 120, 150.0, 150.0, 80.0, 60.0)), 0.1)
            >>> last = torch.full((120, 160), -(2 ** 62))  # no events: every pose costs the cap
            >>> reloc.costs(torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]] * 2), last, 1000).tolist()
            [20.0, 20.0]
        """
        poses = torch.as_tensor(poses, dtype=torch.float64)
        if poses.ndim != 2 or poses.shape[1] != 7 or not len(poses) or last_us.ndim not in (2, 3) \
                or last_us.dtype != torch.int64:
            raise ValueError(f"expected poses (K, 7), K >= 1, and last_us (H, W) or (C, H, W) int64, got "
                             f"{tuple(poses.shape)}, {tuple(last_us.shape)} {last_us.dtype}")
        centre = poses[:1].clone()
        centre[0, :3] = poses[:, :3].mean(0)
        events = self._events(centre, last_us, int(t_now_us))
        got = [self._edges_full(p[None]) for p in poses]
        windows = [g[2] for g in got if g is not None]
        if not windows:
            return torch.full((len(poses),), self.cap_px, dtype=torch.float64)
        # the distances are read at the poses' edge pixels only: within their windows, where the events that can
        # be nearer than the cap lie within the windows grown by the cap (chamfer paths stay in that box: the same
        # numbers as over the whole frame, in a fraction of the time)
        c = math.ceil(self.cap_px)
        u0, v0 = min(w[0] for w in windows) - c, min(w[1] for w in windows) - c
        u1, v1 = max(w[0] + w[2] for w in windows) + c, max(w[1] + w[3] for w in windows) + c
        obs = self._full_res(events, box=(u0, v0, u1, v1))
        return torch.tensor([self._cost_of(g, obs) for g in got], dtype=torch.float64)

    def forward(self, pose: torch.Tensor, last_us: torch.Tensor, t_now_us: torch.Tensor,
                own: torch.Tensor | None = None) -> Relocalisation:
        B = pose.shape[0] if pose.ndim == 2 else -1
        t_now_us = torch.as_tensor(t_now_us)
        own = pose if own is None else own
        if pose.shape != (B, 7) or own.shape != (B, 7) or last_us.ndim not in (3, 4) or last_us.shape[0] != B \
                or t_now_us.shape != (B,) or last_us.dtype != torch.int64:
            raise ValueError(f"expected pose and own (B, 7), last_us (B, H, W) or (B, C, H, W) int64, t_now_us (B,), "
                             f"got {tuple(pose.shape)}, {tuple(own.shape)}, {tuple(last_us.shape)} {last_us.dtype}, "
                             f"{tuple(t_now_us.shape)}")
        if tuple(last_us.shape[-2:]) != (self.camera.height, self.camera.width):
            raise ValueError(f"last_us must be {self.camera.height}x{self.camera.width} (the renderer's camera), got "
                             f"{tuple(last_us.shape[-2:])}")
        with _threads(self.workers) as pool:
            out = [self._one(pose[k:k + 1], own[k:k + 1], last_us[k], int(t_now_us[k]), pool) for k in range(B)]
        best = torch.stack([o[0] for o in out])
        cost = torch.tensor([o[1] for o in out], dtype=torch.float64)
        runner = torch.tensor([o[2] for o in out], dtype=torch.float64)
        clear = (cost <= self.max_cost_px) & (runner - cost >= self.min_margin_px)
        own_cost = torch.tensor([o[3] for o in out], dtype=torch.float64)
        return Relocalisation(best, cost, runner, clear, own_cost)
