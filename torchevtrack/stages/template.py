"""Stage 5: local template correction (EDOPT-style), batched over B and over the 13 hypotheses.

Pipeline of one correction, batched over ``B``. The tensor functions below define each step; the default
path (:func:`template_model`, :func:`quadratic_score`, :func:`newton_search`) runs the same steps as compiled
(numba) loops over the pixels, tested against them:

1. **Canvas.** The object's pixels in a render at the propagated pose (``depth > 0``; the render may be
   a window of the frame whose top-left pixel is ``origin``) give a bounding box; it is grown by
   ``margin_px``, made square and resampled (bilinear, :func:`to_canvas`) into a ``canvas x canvas``
   image. The EROS observation goes through the same box. The canvas is itself a pinhole camera
   (:func:`canvas_intrinsics`), so all geometry below happens in canvas pixels.
2. **Template.** Edge map = ``|Sobel|`` of the grey render together with the ``|Sobel|`` of the
   object mask (silhouette edges, seen even where the object's grey equals the background), i.e.
   ``max(|grad gray|, |grad mask|)``, truncated at ``edge_clip`` and divided by it (so every edge
   with enough contrast counts the same: events fire for any contrast above the threshold). Then a
   Difference of Gaussians widens the edges and adds a negative band around them: kernel sizes
   ``odd(canvas / 20)`` and ``odd(canvas / 8)`` (7 and 17 at 128 px) with OpenCV's default sigma for
   a kernel size (``0.3 ((k - 1) / 2 - 1) + 0.8``: 1.4 and 2.9 px). The DoG is scaled by
   ``0.5 / max`` of the null hypothesis' DoG (one factor for all 13 hypotheses, so no hypothesis is
   favoured by its normalisation; zero stays zero) and clipped to ``[-0.5, 0.5]``. With ``interior > 0`` the
   object's coverage of each canvas pixel, times ``interior``, is added (events inside the outline, e.g. of a print
   the mesh lacks, then count for the object rather than pull its outline inwards).
   Score = ``sum(template * observation)`` over the canvas, less, with ``interior > 0``, ``interior tau`` per canvas
   pixel the object covers (:func:`area_weight`, :func:`newton_kernel`): together the two-rate Poisson likelihood of
   the events on and off the object.
3. **Hypotheses** (:func:`~torchevtrack.reference.hypothesis_steps`): index 0 is the null motion, then ``+/-`` steps
   along ``tx, ty, tz, rx, ry, rz`` (index ``1 + 2 a`` is ``+``, ``2 + 2 a`` is ``-`` for axis ``a``). A step ``[dt,
   phi]`` moves the pose as ``t' = t + dt``, ``q' = exp(phi) (x) q``: a translation in the camera frame, or a
   rotation about a **camera** axis through the **object origin** (the rotation is applied on the left, as
   everywhere in :mod:`torchevtrack.geometry`). Names: pitch = ``rx``, yaw = ``ry``, roll = ``rz`` (the optical
   axis). Step sizes (paper Eqs. 10-11, object motion, so ``+x`` moves the image by ``+dp``): ``dx = z dp / fx``,
   ``dy = z dp / fy``, ``dz = dp / mean_i(|(u_i - cx, v_i - cy)| / Z_i)`` over the object's pixels (Eq. 10 with the
   per-pixel depth ``Z_i``; for a fronto-parallel object it is ``z dp / pbar``), rotations ``dtheta``.
4. **Warp** (:func:`~torchevtrack.reference.warp_canvas`): one render gives all 13 templates. For each canvas pixel ``q`` of a
   hypothesis image, ``q`` is back-projected with the *base* depth at ``q``, moved by the inverse of
   the hypothesis' rigid motion ``T_h T_0^-1`` and projected: that is where ``q``'s content came from
   (inverse warp, ``grid_sample``). Using the base depth instead of the (unknown) hypothesis
   depth at ``q`` is the negated-forward-flow approximation: the position error is second order,
   about ``|flow| * |grad flow|`` (below 0.01 px for one-pixel steps inside a surface). Background
   pixels take the mean object depth of their neighbourhood (radius ``canvas / 16``) or the pose's
   depth, so silhouettes and their negative band move with the object. Disocclusions of a 0.5 deg
   rotation are not modelled. Sampling is **cubic B-spline** interpolation (prefiltered, evaluated
   with four bilinear fetches): the null hypothesis samples the base exactly while a step samples
   between canvas pixels, so the interpolator must neither blur nor sharpen (bilinear blurs and biases
   scores toward the null, torch's bicubic sharpens by about 1 %); the B-spline is flat to ~1e-4 in the
   band of the template. The finished template (DoG output) is warped: the DoG is isotropic, so it
   commutes exactly with the translation and roll warps and up to the scale change (``dp / pbar``, ~1 %)
   with the others.
5. **Update** (:func:`~torchevtrack.reference.select`): ``"argmax"`` (the paper) applies the best of the 13 (the
   null wins ties). ``"group"`` (EDOPT) takes, in each group ``{tx, ry}, {ty, rx}, {rz}, {tz}``, the best of its
   hypotheses and applies it if it beats the null score; the applied steps are composed in that group order
   (translations add, rotations ``exp(phi_4) ... exp(phi_1) (x) q``). ``"newton"`` moves all six axes at once by
   sub-step amounts: the score is fitted by a quadratic in step units from 28 scores around the pose, and the damped
   Newton step, clipped to one step per axis, is applied if its score beats the null
   (:func:`~torchevtrack.reference.newton_step`; compiled: :func:`newton_search`). The argmax moves one axis by one
   whole step per round, so an object that turns and shifts at once needs several rounds; Newton follows both, and
   by fractions of a step. With ``iterations > 1`` the correction repeats around the new pose while the score of the
   corrected pose keeps improving, re-warping the same render (a first-order warp, accurate for a few pixels of
   cumulative motion). Given a bound, a correction's depth stays within ``max_dz`` of a reference depth ``z_ref`` (the
   start pose's unless given; the tracker's bound is ``template.max_depth_speed`` times the period around the last
   measured depth moved on by the prediction): each Newton step's depth is clipped to the band and the next round
   searches the other axes there; the other rules clip the chosen pose's depth and score it there. A depth step is
   ``z dp / pbar``, centimetres for a small distant object, and edges that are not the object's (a hand) pulled the
   depth by that much per update.
6. **Scores without warping** (the production path; item 4 is its torch reference, :mod:`torchevtrack.reference`).
   Around a centre pose ``P`` a step ``delta = [dt, phi]`` moves canvas
   pixel ``q`` by ``J(q) delta`` to first order (the interaction matrix of the canvas intrinsics at
   the render's depth, with the twist ``v = dt - phi x t``, ``w = phi`` of a rotation about the
   object origin ``t``), so the template at ``P (+) delta`` is ``T_P(q - J delta)`` and to second order
   ``S(delta) = s0 - g . delta + delta^T M delta / 2`` with ``s0 = sum O T_P``,
   ``g = sum O J^T grad T_P``, ``M = sum O J^T (Hess T_P) J`` (``O`` the observation canvas).
   ``T_P(q) = T(p(q))`` is the render's template warped to ``P`` (item 4), so by the chain rule
   ``grad T_P = Dw^T grad T`` and ``Hess T_P = Dw^T (Hess T) Dw`` (dropping the warp's curvature), with
   ``Dw = dp / dq`` and ``grad T``, ``Hess T`` the exact derivatives of the B-spline interpolant at ``p``.
   :func:`quadratic_score` sums these terms in one compiled pass over the pixels where ``|O| >= 1e-4``
   (about a seventh of the canvas on EROS weighed by event age), evaluating the warp, the spline (4 x 4 coefficients) and
   ``J`` on the fly (about 0.1 ms for a 128 px canvas), so every iteration re-centres exactly on its pose (:meth:`TemplateModel.at` only moves the
   centre). One render gives a :class:`TemplateModel` (template, its spline coefficients, depth);
   an observation contracts it into a :class:`QuadraticScore`, which scores any pose near its centre in
   microseconds. The model is the Taylor expansion of the warp of item 4 up to the second-order terms of
   the displacement (below 1 % of the first-order ones for these steps); ``tools/bench_template.py``
   compares it with the warp. **Reuse:** a render can serve later updates while
   :meth:`TemplateModel.shift_px` (how far its object points moved) stays small, as the warp
   approximates a render only for small motions.

Example:
    >>> import torch
    >>> from torchevtrack.camera import Camera
    >>> from torchevtrack.stages.template import TemplateCorrector
    >>> cam = Camera(64, 64, 80.0, 80.0, 31.5, 31.5)
    >>> yy, xx = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    >>> square = ((xx - 31.5).abs() < 12) & ((yy - 31.5).abs() < 12)
    >>> inner = ((xx - 31.5).abs() < 11) & ((yy - 31.5).abs() < 11)
    >>> depth = (square * 0.5).float()[None]  # a fronto-parallel square 0.5 m away
    >>> obs = torch.roll((square & ~inner).float(), 1, dims=1)[None]  # its outline, 1 px further right
    >>> pose = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]])
    >>> corrector = TemplateCorrector(cam, canvas=64, margin_px=8, rule="argmax", iterations=1)
    >>> out = corrector(pose, depth, None, (0, 0), obs)
    >>> int(out.index), round(float(out.pose[0, 0]) * 80 / 0.5, 2)  # +x hypothesis: 1 px right
    (1, 1.0)
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.config import RULES, TemplateConfig
from torchevtrack.geometry import (nb_quat_canonical, nb_quat_exp, nb_quat_mul,
                                   nb_quat_to_matrix, quat_canonical, quat_conj, quat_exp, quat_log, quat_mul,
                                   quat_rotate)
from torchevtrack.kernels import ANY_ORDER_FASTMATH, EXACT_FASTMATH, kernel
from torchevtrack.linalg import cholesky, cholesky_solve, eigh
from torchevtrack.stages import canvas_taps

__all__ = [
    "AXES",
    "NUM_HYPOTHESES",
    "NEWTON_DAMPING",
    "NEWTON_MAX_STEP",
    "RULES",
    "Correction",
    "render_window",
    "window_extent",
    "window_of",
    "window_kernel",
    "render_scale",
    "canvas_intrinsics",
    "to_canvas",
    "odd_size",
    "gaussian_taps",
    "fill_kernel",
    "PREFILTER_RADIUS",
    "prefilter_taps",
    "apply_steps",
    "pose_delta",
    "QuadraticScore",
    "quadratic_score",
    "TemplateModel",
    "template_model",
    "camera_array",
    "render_box",
    "model_in_box",
    "box_kernel",
    "model_kernel",
    "model_filters",
    "newton_search",
    "area_weight",
    "newton_arrays",
    "newton_kernel",
    "correct_canvas",
    "TemplateCorrector",
    "check_options",
    "check_poses",
    "check_correct",
    "check_images",
    "batch_origin",
]

AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
NUM_HYPOTHESES = 1 + 2 * len(AXES)
NEWTON_DAMPING, NEWTON_MAX_STEP = 0.5, 1.0  # the Newton step's damping and step clip (hypothesis steps per axis)


class Correction(NamedTuple):
    """Result of a template correction (:func:`correct_canvas`, :class:`TemplateCorrector`).

    Attributes:
        pose: ``(B, 7)`` corrected pose.
        score: ``(B,)`` template score of the corrected pose.
        scores: ``(B, 13)`` scores of the hypotheses around the input pose (first iteration).
        index: ``(B,)`` int64, best of those 13 (0 = null).
        applied: ``(B, 13)`` bool, hypotheses applied in the first iteration (one-hot or none for
            ``"argmax"``; up to one per group for ``"group"``; none for ``"newton"``, whose step is
            not one of them: ``iterations`` tells whether it moved).
        iterations: ``(B,)`` int64, number of iterations that moved the pose.
    """

    pose: torch.Tensor
    score: torch.Tensor
    scores: torch.Tensor
    index: torch.Tensor
    applied: torch.Tensor
    iterations: torch.Tensor


# -- regions ----------------------------------------------------------------------------------
def render_window(pose: torch.Tensor, camera: Camera, radius: float | torch.Tensor, margin_px: int = 24) -> torch.Tensor:
    """Window ``(u0, v0, w, h)`` of the frame that contains the object, to render only that region.

    The object is bounded by a sphere of ``radius`` metres around the pose origin (one radius, or ``(B,)``
    per pose); the window is the square around its projection (conservative: half-size ``f r / (z - r)``)
    plus ``margin_px``.

    Shape: ``(B, 7) -> (B, 4)`` int64.
    """
    pose = check_poses(pose, "pose")
    if isinstance(radius, torch.Tensor):
        if radius.shape != pose.shape[:1] or not bool((radius > 0).all()):
            raise ValueError(f"radius must be positive (metres), one per pose, got {radius}")
        radius = radius.detach().double().numpy()
    elif not radius > 0:
        raise ValueError(f"radius must be positive (metres), got {radius}")
    return torch.from_numpy(window_of(pose[:, :3].detach().double().numpy(), camera, radius, margin_px))


def window_of(t: np.ndarray, camera: Camera, radius: float | np.ndarray, margin_px: int,
              clip: bool = False) -> np.ndarray:
    """:func:`render_window` of the object positions ``t`` ``(B, 3)`` (metres, ``z > 0``), unchecked, in one compiled
    call; with ``clip`` moved and cut to lie inside the frame (the size first cut to the frame's, then the corner
    moved in).

    Shape: ``(B, 3), (), () or (B,) -> (B, 4)`` int64.
    """
    out = np.empty((len(t), 4), dtype=np.int64)
    window_kernel(np.ascontiguousarray(t, dtype=np.float64), np.broadcast_to(np.asarray(radius, np.float64), len(t)),
                  camera.fx, camera.fy, camera.cx, camera.cy, float(margin_px), camera.width, camera.height, clip, out)
    return out


@kernel
def window_kernel(t, radius, fx, fy, cx, cy, margin, W, H, clip, out):
    """:func:`window_of` into ``out`` ``(B, 4)`` int64 ``(u0, v0, w, h)``: the square around the projected bounding
    sphere plus ``margin`` pixels; ``t`` ``(B, 3)`` float64 object positions (m), ``radius`` ``(B,)`` float64 (m), the
    frame's intrinsics ``fx, fy, cx, cy`` and size ``W, H``, ``clip`` as for :func:`window_of`."""
    for b in range(t.shape[0]):
        r = radius[b]
        z = max(t[b, 2], r * 1.05)
        for a, f, c in ((0, fx, cx), (1, fy, cy)):
            centre = f * t[b, a] / t[b, 2] + c
            half = f * (r / (z - r)) + margin
            lo = math.floor(centre - half)
            out[b, a], out[b, 2 + a] = lo, math.ceil(centre + half) - lo + 1
        if clip:
            out[b, 2], out[b, 3] = min(out[b, 2], W), min(out[b, 3], H)
            out[b, 0], out[b, 1] = min(max(out[b, 0], 0), W - out[b, 2]), min(max(out[b, 1], 0), H - out[b, 3])


@kernel
def render_scale(w, h, canvas):
    """The subsampling ``s`` (an int >= 1) of the render a template model of ``canvas`` pixels is made from, for a
    render window of ``w x h`` frame pixels: ``max(1, (min(w, h) + canvas) // (2 canvas))``, ``min(w, h) / (2
    canvas)`` rounded, so that a render pixel stays at most two thirds of a canvas pixel of a window-sized box (a
    window holds the object's bounding sphere and a margin; the box, its outline and a margin): windows of 384 px
    and more render at half resolution or less for a 128 px canvas. The window is then rendered at ``ceil(h / s) x
    ceil(w / s)`` pixels, render pixel ``(i, j)`` centred on frame pixel ``(u0 + s j + (s - 1) / 2, v0 + s i + (s -
    1) / 2)``.

    >>> [render_scale(w, h, 128) for w, h in ((283, 283), (400, 420), (514, 514), (1280, 720))]
    [1, 2, 2, 3]
    """
    return max(1, (min(w, h) + canvas) // (2 * canvas))


@kernel(fastmath=EXACT_FASTMATH)
def window_extent(depth, u0, v0, cx, cy, gain):
    """The object's extent in one render window ``depth`` ``(h, w)`` whose top-left frame pixel is ``(u0, v0)``
    (compiled; :func:`~torchevtrack.reference.canvas_box` and :func:`~torchevtrack.reference.radial_gain` reduce it):
    ``(umin, umax, vmin, vmax, total, n)`` floats, the window pixel bounds of the ``n`` object pixels (``depth > 0``;
    all 0 if none) and, with ``gain``, ``total`` the sum of their ``|(u - cx, v - cy)| / z`` (else 0)."""
    h, w = depth.shape
    umin, umax, vmin, vmax, total, n = w, -1, h, -1, 0.0, 0
    for v in range(h):
        row = depth[v]
        lo, hi = 0, w - 1  # the row's first and last object pixel
        while lo < w and not row[lo] > 0:
            lo += 1
        if lo == w:
            continue
        while not row[hi] > 0:
            hi -= 1
        umin, umax, vmin, vmax = min(umin, lo), max(umax, hi), min(vmin, v), v
        dv = v + v0 - cy
        for u in range(lo, hi + 1):
            z = row[u]
            if z > 0:
                du = u + u0 - cx
                n += 1
                total += math.sqrt(du * du + dv * dv) / z
    if n == 0:
        umin = umax = vmin = vmax = 0
    return float(umin), float(umax), float(vmin), float(vmax), total if gain else 0.0, float(n)


def canvas_intrinsics(box: torch.Tensor, camera: Camera, canvas: int) -> torch.Tensor:
    """Pinhole intrinsics ``[fx, fy, cx, cy]`` of the canvas cut from ``box`` (see :func:`to_canvas`).

    Shape: ``(B, 3) -> (B, 4)``, pixels of the canvas.
    """
    s = box[:, 2] / canvas
    half = canvas / 2.0 - 0.5
    return torch.stack(
        (camera.fx / s, camera.fy / s, (camera.cx - box[:, 0]) / s + half, (camera.cy - box[:, 1]) / s + half), -1
    )


def to_canvas(image: torch.Tensor, box: torch.Tensor, canvas: int, origin=(0, 0)) -> torch.Tensor:
    """Resample the square ``box`` of an image (or window of the frame) into a ``canvas`` px square.

    Canvas pixel ``i`` samples frame coordinate ``cu + (i + 0.5 - canvas / 2) * side / canvas``
    (bilinear; zero outside the image).

    Args:
        image: ``(B, h, w)`` or ``(B, C, h, w)``, the window of the frame with top-left ``origin``.
        box: ``(B, 3)`` ``[cu, cv, side]`` in frame pixels (:func:`~torchevtrack.reference.canvas_box`).
        canvas: output size in pixels.
        origin: ``(B, 2)`` or ``(2,)`` frame coordinates of the image's pixel ``(0, 0)``.

    Shape: ``(B, [C,] h, w) -> (B, [C,] canvas, canvas)``.
    """
    squeeze = image.ndim == 3
    x = image[:, None] if squeeze else image
    if x.ndim != 4 or not x.is_floating_point():
        raise ValueError(f"image must be a float tensor (B, h, w) or (B, C, h, w), got {tuple(image.shape)}")
    B, _, h, w = x.shape
    if box.shape != (B, 3):
        raise ValueError(f"box must have shape ({B}, 3) [cu, cv, side], got {tuple(box.shape)}")
    origin = batch_origin(origin, B, x.dtype)
    box = box.to(x.dtype)
    offs = (torch.arange(canvas, dtype=x.dtype) + 0.5 - canvas / 2.0) * (box[:, 2:] / canvas)  # (B, N)
    u = box[:, :1] + offs - origin[:, :1]
    v = box[:, 1:2] + offs - origin[:, 1:]
    gx = ((2 * u + 1) / w - 1)[:, None, :].expand(B, canvas, canvas)
    gy = ((2 * v + 1) / h - 1)[:, :, None].expand(B, canvas, canvas)
    out = F.grid_sample(x, torch.stack((gx, gy), -1), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[:, 0] if squeeze else out


# -- templates --------------------------------------------------------------------------------
def odd_size(n: float) -> int:
    """The odd kernel size nearest ``n`` from above (at least 3): the DoG's sizes ``odd_size(canvas / 20)`` and
    ``odd_size(canvas / 8)``."""
    k = max(3, round(n))
    return k if k % 2 else k + 1


@functools.lru_cache(maxsize=16)
def gaussian_taps(k: int, dtype: torch.dtype) -> torch.Tensor:
    """Normalised Gaussian kernel of odd size ``k``, sigma ``0.3 ((k - 1) / 2 - 1) + 0.8`` (OpenCV's default;
    cached constant, never modified in place).

    Shape: ``(k,)`` in ``dtype``.
    """
    s = 0.3 * ((k - 1) / 2 - 1) + 0.8
    x = torch.arange(k, dtype=torch.float64) - k // 2
    g = torch.exp(-x * x / (2 * s * s))
    return (g / g.sum()).to(dtype)


# -- hypotheses -------------------------------------------------------------------------------


def apply_steps(pose: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """Poses moved by steps ``[dt, phi]``: ``t' = t + dt``, ``q' = exp(phi) (x) q``.

    Shape: ``(B, 7), (B, K, 6) -> (B, K, 7)``.
    """
    steps = steps.to(pose.dtype)
    t = pose[:, None, :3] + steps[..., :3]
    q = quat_mul(quat_exp(steps[..., 3:]), pose[:, None, 3:])
    return torch.cat((t, quat_canonical(q)), -1)


# -- warping and scoring ----------------------------------------------------------------------
@kernel
def fill_kernel(depth, fallback, r):
    """The background fill of one canvas depth ``depth`` ``(h, w)``, in place (compiled): each background pixel
    (``<= 0``) takes the mean object depth in the ``(2 r + 1)`` square around it, or ``fallback`` (metres) where that
    square holds no object pixel (:func:`~torchevtrack.reference._fill_depth` fills a batch with it). From float64 box
    sums of the object depths and counts: running sums over ``2 r + 1`` rows, then prefix sums along the rows
    (zero-padded by ``r``, so the window of pixel ``u`` is ``P[u + 2 r + 1] - P[u]``)."""
    h, w = depth.shape
    S, C = np.zeros((h, w + 2 * r + 1)), np.zeros((h, w + 2 * r + 1))
    s, c = np.zeros(w), np.zeros(w)  # sums over the rows [v - r, v + r]
    for v in range(-r, h):
        if v + r < h:
            row = depth[v + r]
            for u in range(w):
                z = row[u]
                s[u] += z if z > 0 else 0.0
                c[u] += 1.0 if z > 0 else 0.0
        if v - r - 1 >= 0:
            row = depth[v - r - 1]
            for u in range(w):
                z = row[u]
                s[u] -= z if z > 0 else 0.0
                c[u] -= 1.0 if z > 0 else 0.0
        if v >= 0:
            S[v, r + 1:r + 1 + w] = s
            C[v, r + 1:r + 1 + w] = c
    for u in range(1, w + 2 * r + 1):  # independent across rows
        for v in range(h):
            S[v, u] += S[v, u - 1]
            C[v, u] += C[v, u - 1]
    for v in range(h):
        row, S0, S1, C0, C1 = depth[v], S[v], S[v, 2 * r + 1:], C[v], C[v, 2 * r + 1:]
        for u in range(w):
            n = C1[u] - C0[u]
            z = row[u]
            row[u] = z if z > 0 else ((S1[u] - S0[u]) / n if n > 0.5 else fallback)


# Cubic B-spline interpolation for the warp (module docstring, item 4): exact at the samples and
# neither blurring nor sharpening a sub-pixel sample of the smooth template.
_POLE = math.sqrt(3.0) - 2.0
PREFILTER_RADIUS = 8  # of prefilter_taps; |pole| ** 9 < 1e-5: truncation error of the FIR inverse of [1, 4, 1] / 6


@functools.lru_cache(maxsize=8)
def prefilter_taps(dtype: torch.dtype) -> torch.Tensor:
    """FIR taps of the cubic B-spline prefilter (the inverse of ``[1, 4, 1] / 6`` truncated at ``PREFILTER_RADIUS``;
    cached constant, never modified in place).

    Shape: ``(2 PREFILTER_RADIUS + 1,)`` in ``dtype``.
    """
    k = torch.arange(-PREFILTER_RADIUS, PREFILTER_RADIUS + 1, dtype=torch.float64)
    return ((-6 * _POLE / (1 - _POLE**2)) * _POLE ** k.abs()).to(dtype)


# -- second-order score model (module docstring, item 6) --------------------------------------
# Observed pixels weaker than this are left out of the score sums. On EROS weighed by event age (tracker,
# mustard_fast) it halves the pixels visited (14 % of the canvas instead of 31 %) and drops 0.08 % of the
# observation's mass.
_MIN_OBSERVATION = 1e-4


@kernel
def _bspline_weights(x):
    """Cubic B-spline weights of the taps ``i - 1 .. i + 2`` at ``i + x`` (``0 <= x < 1``, float32), and their first
    and second derivatives: three 4-tuples of float32."""
    f4 = np.float32
    one, half = f4(1.0), f4(0.5)
    x2 = x * x
    w0, w3 = (one - x) ** 3 * f4(1 / 6), x2 * x * f4(1 / 6)
    w1 = f4(2 / 3) - x2 + x2 * x * half
    return ((w0, w1, one - w0 - w1 - w3, w3),
            (-(one - x) ** 2 * half, f4(-2.0) * x + f4(1.5) * x2, half + x - f4(1.5) * x2, x2 * half),
            (one - x, f4(3.0) * x - f4(2.0), one - f4(3.0) * x, x))


@kernel
def _rotation(q):
    """Rotation matrix of a ``(w, x, y, z)`` quaternion (normalised first)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return nb_quat_to_matrix(q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@kernel
def _pixel_motion(e0, e2, Ar, A2, d0, d1, d2):
    """One row of ``G = dp / d delta`` (:func:`_quadratic_terms`): with ``dp_r / dY = e0`` along ``r`` and ``e2``
    along z, ``P = e0 A[r] + e2 A[2]`` and the row is ``[-P, P x d]``, ``d = X - t``. A 6-tuple."""
    P0, P1, P2 = e0 * Ar[0] + e2 * A2[0], e0 * Ar[1] + e2 * A2[1], e0 * Ar[2] + e2 * A2[2]
    return -P0, -P1, -P2, P1 * d2 - P2 * d1, P2 * d0 - P0 * d2, P0 * d1 - P1 * d0


# Pixels per block of :func:`_quadratic_terms`: its scratch (39 rows of _BLOCK float32) stays in the L1 cache.
_BLOCK = 64


@kernel
def _tap_rows(c, r, w, d, dd):
    """One row of spline taps (``c[r]``, ``c[r + _BLOCK]``, ... :func:`_quadratic_terms`) contracted with the
    weights ``w``, ``d``, ``dd`` along ``u``: three numbers."""
    B = _BLOCK
    k0, k1, k2, k3 = c[r], c[r + B], c[r + 2 * B], c[r + 3 * B]
    return (k0 * w[0] + k1 * w[1] + k2 * w[2] + k3 * w[3], k0 * d[0] + k1 * d[1] + k2 * d[2] + k3 * d[3],
            k0 * dd[0] + k1 * dd[1] + k2 * dd[2] + k3 * dd[3])


@kernel(fastmath=ANY_ORDER_FASTMATH, inline="always")
def _hessian_row(c, nb, k, Tu, Tv, Tuu, Tuv, Tvv):
    """Block sums of :func:`_quadratic_terms`' ``g[k]`` (``O grad T . G[k]``) and row ``k`` of ``M``
    (``hu G_u + hv G_v`` with ``hu = T_uu G_u[k] + T_uv G_v[k]``, ``hv = T_uv G_u[k] + T_vv G_v[k]``), float32: seven
    numbers."""
    B = _BLOCK
    gk = m0 = m1 = m2 = m3 = m4 = m5 = np.float32(0.0)
    for i in range(nb):
        Gu, Gv = c[k * B + i], c[(6 + k) * B + i]
        gk += Tu[i] * Gu + Tv[i] * Gv
        hu, hv = Tuu[i] * Gu + Tuv[i] * Gv, Tuv[i] * Gu + Tvv[i] * Gv
        m0 += hu * c[i] + hv * c[6 * B + i]
        m1 += hu * c[B + i] + hv * c[7 * B + i]
        m2 += hu * c[2 * B + i] + hv * c[8 * B + i]
        m3 += hu * c[3 * B + i] + hv * c[9 * B + i]
        m4 += hu * c[4 * B + i] + hv * c[10 * B + i]
        m5 += hu * c[5 * B + i] + hv * c[11 * B + i]
    return gk, m0, m1, m2, m3, m4, m5


@kernel
def _observed_points(Z, K, obs):
    """The observed canvas pixels of one element (``|O| >= _MIN_OBSERVATION``, ``obs`` ``(N * N,)``) in raster
    order: their observation ``o`` ``(n,)`` and the point ``X`` ``(3, n)`` (metres) back-projected with the
    render's depth ``Z`` ``(N, N)`` into the frame of the pose being scored (independent of that pose)."""
    N = Z.shape[0]
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    at = np.empty(N * N, dtype=np.int32)
    n = 0
    for q in range(N * N):  # their indices, compacted without branches (which would mispredict)
        at[n] = q
        n += abs(obs[q]) >= _MIN_OBSERVATION
    o = np.empty(n)
    X = np.empty((3, n))
    for k in range(n):
        q = at[k]
        v, u = q // N, q % N
        z = Z[v, u]
        o[k] = obs[q]
        X[0, k], X[1, k], X[2, k] = z * (u - cx) / fx, z * (v - cy) / fy, z
    return o, X


@kernel(fastmath=ANY_ORDER_FASTMATH, inline="always")
def _quadratic_terms(coef, K, render_pose, pose, o, X):
    """Taylor terms ``(s0, g (6,), M (6, 6))`` of one element's warped-template score around ``pose``.

    ``coef``: ``(N + 6, N + 6)`` spline coefficients zero-padded by 3 pixels (:attr:`TemplateModel.coef`);
    ``o``, ``X``: the observed pixels (:func:`_observed_points`). For every observed pixel: the point
    ``Y = A X + b`` in the render's frame and its canvas pixel ``p``, the cubic B-spline of the render
    template at ``p`` (value, gradient and Hessian from the 4 x 4 coefficients ``coef`` around ``p``), and
    ``G = dp / d delta``: a step ``delta = [dt, phi]`` of the centre moves the sampled point by
    ``-dt - phi x (X - t)`` in the centre's frame. Sums ``O T`` into ``s0``, ``-O G^T grad T`` into ``g``
    and ``O G^T (Hess T) G`` into ``M`` (module docstring, item 6).

    The pixels go in blocks of ``_BLOCK``, each pass over a block a loop the compiler vectorises (except the
    gather of the taps), with per-pixel values in rows of the flat scratch ``c`` (row ``r``, pixel ``i`` at
    ``c[r * _BLOCK + i]``; constant offsets let the compiler see that rows do not overlap): 0-5 the row
    ``G_u``, 6-11 ``G_v``, 12 ``O`` (0 off the canvas), 13-14 the spline fractions, 15-16 the first taps,
    17-32 the 4 x 4 taps, 33-38 ``O`` times ``T, T_u, T_v, T_uu, T_uv, T_vv``. The warp is float64; the
    per-pixel terms and a block's sums are float32 (twice the vector lanes; the template is float32, and a
    block's sums round at ~1e-7), the totals float64. Of the symmetric ``M`` only the upper triangle is summed.
    Inlined into its callers, which sum in any order (:data:`~torchevtrack.kernels.ANY_ORDER_FASTMATH`): a copy
    optimised apart from them could sum in another (:mod:`torchevtrack.kernels`).
    """
    N = coef.shape[0] - 6
    B = _BLOCK
    fx, fy, cx, cy = K[0], K[1], K[2], K[3]
    A = _rotation(render_pose[3:]) @ _rotation(pose[3:]).T  # centre frame -> render frame
    off = render_pose[:3] - A @ pose[:3]
    # scalars and tuples: loop-invariant values the compiler can keep in registers
    A0, A1, A2 = (A[0, 0], A[0, 1], A[0, 2]), (A[1, 0], A[1, 1], A[1, 2]), (A[2, 0], A[2, 1], A[2, 2])
    off0, off1, off2, t0, t1, t2 = off[0], off[1], off[2], pose[0], pose[1], pose[2]
    s0 = 0.0
    g = np.zeros(6)
    M = np.zeros((6, 6))
    c = np.empty(39 * B, dtype=np.float32)
    for p0 in range(0, o.shape[0], B):
        nb = min(B, o.shape[0] - p0)
        for i in range(nb):
            X0, X1, X2 = X[0, p0 + i], X[1, p0 + i], X[2, p0 + i]
            Y0 = A0[0] * X0 + A0[1] * X1 + A0[2] * X2 + off0
            Y1 = A1[0] * X0 + A1[1] * X1 + A1[2] * X2 + off1
            iz = 1.0 / max(A2[0] * X0 + A2[1] * X1 + A2[2] * X2 + off2, 1e-9)
            pu, pv = fx * Y0 * iz + cx, fy * Y1 * iz + cy
            # coef is zero-padded by 3: the taps iu - 1 .. iu + 2 of p are at iu + 2 .. iu + 5
            iu, iv = math.floor(pu), math.floor(pv)
            c[12 * B + i] = o[p0 + i] if iu >= -2 and iu <= N and iv >= -2 and iv <= N else 0.0  # else no tap inside
            iu, iv = min(max(iu, -2.0), N), min(max(iv, -2.0), N)
            c[13 * B + i], c[14 * B + i], c[15 * B + i], c[16 * B + i] = pu - iu, pv - iv, iu + 2, iv + 2
            # G = dp/dY A [-I, [X - t]x], row by row
            d0, d1, d2 = X0 - t0, X1 - t1, X2 - t2
            c[i], c[B + i], c[2 * B + i], c[3 * B + i], c[4 * B + i], c[5 * B + i] = _pixel_motion(
                fx * iz, -fx * Y0 * iz * iz, A0, A2, d0, d1, d2)
            c[6 * B + i], c[7 * B + i], c[8 * B + i], c[9 * B + i], c[10 * B + i], c[11 * B + i] = _pixel_motion(
                fy * iz, -fy * Y1 * iz * iz, A1, A2, d0, d1, d2)
        for i in range(nb):
            iu, iv = int(c[15 * B + i]), int(c[16 * B + i])
            for j in range(4):
                for k in range(4):
                    c[(17 + 4 * j + k) * B + i] = coef[iv + j, iu + k]
        for i in range(nb):
            wu, du, ddu = _bspline_weights(c[13 * B + i])
            wv, dv, ddv = _bspline_weights(c[14 * B + i])
            a0, a1, a2 = _tap_rows(c, 17 * B + i, wu, du, ddu)
            b0, b1, b2 = _tap_rows(c, 21 * B + i, wu, du, ddu)
            e0, e1, e2 = _tap_rows(c, 25 * B + i, wu, du, ddu)
            h0, h1, h2 = _tap_rows(c, 29 * B + i, wu, du, ddu)
            w = c[12 * B + i]
            c[33 * B + i] = w * (a0 * wv[0] + b0 * wv[1] + e0 * wv[2] + h0 * wv[3])
            c[34 * B + i] = w * (a1 * wv[0] + b1 * wv[1] + e1 * wv[2] + h1 * wv[3])
            c[35 * B + i] = w * (a0 * dv[0] + b0 * dv[1] + e0 * dv[2] + h0 * dv[3])
            c[36 * B + i] = w * (a2 * wv[0] + b2 * wv[1] + e2 * wv[2] + h2 * wv[3])
            c[37 * B + i] = w * (a1 * dv[0] + b1 * dv[1] + e1 * dv[2] + h1 * dv[3])
            c[38 * B + i] = w * (a0 * ddv[0] + b0 * ddv[1] + e0 * ddv[2] + h0 * ddv[3])
        acc = np.float32(0.0)
        for i in range(nb):
            acc += c[33 * B + i]
        s0 += acc
        # g and the upper triangle of M: rows 0-2 (their unused lower entries are three sums), then rows 3-5 together
        Tu, Tv, Tuu = c[34 * B:34 * B + nb], c[35 * B:35 * B + nb], c[36 * B:36 * B + nb]
        Tuv, Tvv = c[37 * B:37 * B + nb], c[38 * B:38 * B + nb]
        g0, m00, m01, m02, m03, m04, m05 = _hessian_row(c, nb, 0, Tu, Tv, Tuu, Tuv, Tvv)
        g1, _, m11, m12, m13, m14, m15 = _hessian_row(c, nb, 1, Tu, Tv, Tuu, Tuv, Tvv)
        g2, _, _, m22, m23, m24, m25 = _hessian_row(c, nb, 2, Tu, Tv, Tuu, Tuv, Tvv)
        g3 = g4 = g5 = m33 = m34 = m35 = m44 = m45 = m55 = np.float32(0.0)
        for i in range(nb):
            Gu, Gv, Fu, Fv = c[3 * B + i], c[9 * B + i], c[4 * B + i], c[10 * B + i]
            Eu, Ev = c[5 * B + i], c[11 * B + i]
            g3 += Tu[i] * Gu + Tv[i] * Gv
            g4 += Tu[i] * Fu + Tv[i] * Fv
            g5 += Tu[i] * Eu + Tv[i] * Ev
            hu, hv = Tuu[i] * Gu + Tuv[i] * Gv, Tuv[i] * Gu + Tvv[i] * Gv
            m33 += hu * Gu + hv * Gv
            m34 += hu * Fu + hv * Fv
            m35 += hu * Eu + hv * Ev
            hu, hv = Tuu[i] * Fu + Tuv[i] * Fv, Tuv[i] * Fu + Tvv[i] * Fv
            m44 += hu * Fu + hv * Fv
            m45 += hu * Eu + hv * Ev
            m55 += (Tuu[i] * Eu + Tuv[i] * Ev) * Eu + (Tuv[i] * Eu + Tvv[i] * Ev) * Ev
        for k, gk in enumerate((g0, g1, g2, g3, g4, g5)):
            g[k] -= gk
        for k, m, v in ((0, 0, m00), (0, 1, m01), (0, 2, m02), (0, 3, m03), (0, 4, m04), (0, 5, m05), (1, 1, m11),
                        (1, 2, m12), (1, 3, m13), (1, 4, m14), (1, 5, m15), (2, 2, m22), (2, 3, m23), (2, 4, m24),
                        (2, 5, m25), (3, 3, m33), (3, 4, m34), (3, 5, m35), (4, 4, m44), (4, 5, m45), (5, 5, m55)):
            M[k, m] += v
    for k in range(6):
        for m in range(k + 1, 6):
            M[m, k] = M[k, m]
    return s0, g, M


@kernel(fastmath=ANY_ORDER_FASTMATH)
def _quadratic_kernel(coef, Z, K, render_pose, pose, obs, s0, g, M):
    """:func:`_quadratic_terms` of every batch element into ``s0`` ``(B,)``, ``g`` ``(B, 6)``, ``M`` ``(B, 6, 6)``."""
    for b in range(coef.shape[0]):
        o, X = _observed_points(Z[b], K[b], obs[b])
        s0[b], g[b], M[b] = _quadratic_terms(coef[b], K[b], render_pose[b], pose[b], o, X)


@kernel
def _apply_step(pose, delta):
    """:func:`apply_steps` of one step ``[dt, phi]`` to one pose (float64)."""
    out = np.empty(7)
    out[:3] = pose[:3] + delta[:3]
    e0, e1, e2, e3 = nb_quat_exp(delta[3], delta[4], delta[5])
    q0, q1, q2, q3 = nb_quat_mul(e0, e1, e2, e3, pose[3], pose[4], pose[5], pose[6])
    out[3], out[4], out[5], out[6] = nb_quat_canonical(q0, q1, q2, q3)
    return out


@kernel(fastmath={"reassoc", "nsz"}, inline="always")
def area_weight(obs, valid, N, interior):
    """The area term's weight ``a = interior tau A`` of one element (see :func:`newton_kernel`), float64.

    ``obs`` ``(N * N,)`` the canvas observation, ``valid`` ``(P,)`` the model's object points (the canvas grid of
    :func:`model_kernel`, every ``max(1, N // 16)``-th pixel): a canvas pixel is on the object when its grid cell's
    point is. ``A`` is the object's area (canvas pixels), ``rho_f`` and ``rho_b`` the mean observation on and off
    it (``rho_b`` at least ``1e-5``) and ``tau = (rho_f - rho_b) / log(rho_f / rho_b)``, the density at which a pixel
    is as likely the object's as the background's under two Poisson rates (0 when ``rho_f <= rho_b``). Its sums go in
    any order: inlined into :func:`newton_kernel` (under its flags), called from Python on its own.
    """
    if interior == 0.0:
        return 0.0
    step = max(1, N // 16)
    n1 = (N - step // 2 + step - 1) // step
    total = on = 0.0  # sums in any order (vectorised)
    for i in range(N * N):
        total += obs[i]
    area = 0
    for r in range(n1):  # the object's cells: blocks of step x step pixels (the last row and column take the rest)
        v1 = N if r == n1 - 1 else (r + 1) * step
        for c in range(n1):
            if valid[r * n1 + c]:
                u1 = N if c == n1 - 1 else (c + 1) * step
                for v in range(r * step, v1):
                    for u in range(c * step, u1):
                        on += obs[v * N + u]
                area += (v1 - r * step) * (u1 - c * step)
    off = total - on
    if area == 0:
        return 0.0
    rho_f = on / area
    rho_b = max(off / max(N * N - area, 1), 1e-5)
    if not rho_f > rho_b:
        return 0.0
    return interior * (rho_f - rho_b) / math.log(rho_f / rho_b) * area


@kernel(fastmath=ANY_ORDER_FASTMATH)
def newton_kernel(coef, Z, K, render_pose, pose, obs, gain, fx, fy, dp, dtheta, iterations, damping, max_step,
                  max_dz, z_ref, valid, interior, out_pose, out_score, out_scores, out_moved):
    """:func:`newton_search` on numpy arrays, unchecked, into ``out_pose`` ``(B, 7)``, ``out_score`` ``(B,)``,
    ``out_scores`` ``(B, 13)`` (float64) and ``out_moved`` ``(B,)`` int64; releases the GIL. The model's fields
    (``coef``, ``Z = depth``, ``K`` float64, ``render_pose``, ``gain`` float64), the start poses ``pose`` ``(B, 7)``
    float64, ``obs`` ``(B, N * N)``, the frame's ``fx, fy``, the steps ``dp`` (pixels) and ``dtheta`` (radians), and
    ``iterations, damping, max_step, max_dz`` and the band centres ``z_ref`` ``(B,)`` float64 as for
    :func:`newton_search`, the model's ``valid`` object points and the ``interior`` weights ``(B,)`` float64 of its
    template.

    The ``"newton"`` rule of :func:`~torchevtrack.reference.search` on the exact second-order model, per element.
    With ``interior > 0`` the score also pays ``tau`` per canvas pixel the object covers (:func:`area_weight`): the
    term ``-a (z_r / z)^2`` of a pose at depth ``z`` (the render's ``z_r``: the area scales with the inverse square
    of the depth), added to each round's model as its second-order Taylor terms in ``tz``.

    Each round fits the model at the current pose (:func:`_quadratic_terms`), where in step units ``u`` the score is
    ``s0 + gu . u + u^T Hu u / 2`` with ``gu = -g unit``, ``Hu = unit M unit``; the damped step ``u = (lambda I -
    Hu)^-1 gu`` (:func:`~torchevtrack.reference.newton_step`'s ``lambda``), clipped per axis, is taken if its score
    beats ``s0``, else the search stops. ``unit`` holds the hypothesis step sizes of the start pose per axis
    (:func:`~torchevtrack.reference.hypothesis_steps` of ``gain``, the frame's ``fx``, ``fy``, ``dp`` pixels and
    ``dtheta`` radians); the translation units scale with the current depth. Each round's depth step is then clipped
    so that the pose stays within ``max_dz`` metres of ``z_ref`` (the other axes keep their step, and the next round
    is searched at the clipped depth).
    """
    for b in range(coef.shape[0]):
        z = pose[b, 2]
        unit = np.array([z * dp / fx, z * dp / fy, dp / max(gain[b], 1e-12) if gain[b] > 0 else 0.0,
                         dtheta, dtheta, dtheta])
        cur = pose[b].copy()
        moved = 0
        o, X = _observed_points(Z[b], K[b], obs[b])
        area = area_weight(obs[b], valid[b], Z.shape[-1], interior[b])
        gu, step, delta = np.empty(6), np.empty(6), np.empty(6)
        Hu, A, L, work, vecs = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
        eig = np.empty(6)
        for it in range(iterations):
            s0, g, M = _quadratic_terms(coef[b], K[b], render_pose[b], cur, o, X)
            if area > 0.0:  # -a (z_r / z)^2 around z = cur's depth: s0 - g . delta + delta^T M delta / 2 in tz
                zc = cur[2]
                ac = area * (render_pose[b, 2] / zc) ** 2
                s0 -= ac
                g[2] -= 2.0 * ac / zc
                M[2, 2] -= 6.0 * ac / (zc * zc)
            un = unit.copy()
            un[:2] *= cur[2] / pose[b, 2]
            if it == 0:
                out_score[b] = s0
                out_scores[b, 0] = s0
                for a in range(6):
                    for sign in range(2):
                        d = un[a] * (1.0 - 2.0 * sign)
                        out_scores[b, 1 + 2 * a + sign] = s0 - g[a] * d + 0.5 * M[a, a] * d * d
            for i in range(6):
                gu[i] = -g[i] * un[i]
                for j in range(6):
                    Hu[i, j] = M[i, j] * un[i] * un[j]
            mean_curv = 0.0
            for i in range(6):
                mean_curv += abs(Hu[i, i])
            work[:] = Hu
            eigh(work, eig, vecs)
            top = eig[0]
            for i in range(1, 6):
                top = max(top, eig[i])
            lam = max(top, 0.0) + damping * mean_curv / 6 + 1e-12
            for i in range(6):  # lambda I - Hu, from Hu's lower triangle (all that its Cholesky factor reads)
                for j in range(i + 1):
                    A[i, j] = A[j, i] = -Hu[i, j]
                A[i, i] += lam
            if not cholesky(A, L):  # positive definite by construction, unless the terms are not finite
                break
            cholesky_solve(L, gu, step)
            for i in range(6):
                delta[i] = min(max(step[i], -max_step), max_step) * un[i]
            delta[2] = min(max(delta[2], z_ref[b] - max_dz - cur[2]), z_ref[b] + max_dz - cur[2])
            gd = dMd = 0.0  # g . delta and delta^T M delta (small loops: no BLAS calls)
            for i in range(6):
                gd += g[i] * delta[i]
                Md = 0.0
                for j in range(6):
                    Md += M[i, j] * delta[j]
                dMd += delta[i] * Md
            new = s0 - gd + 0.5 * dMd
            if not new > s0:
                break
            cur = _apply_step(cur, delta)
            out_score[b] = new
            moved += 1
        out_pose[b] = cur
        out_moved[b] = moved


def quadratic_score(coef: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, render_pose: torch.Tensor,
                    pose: torch.Tensor, obs: torch.Tensor) -> "QuadraticScore":
    """Second-order model of the template score around ``pose``, from a render's template made at ``render_pose``.

    The template at ``pose`` is the render's template warped there (:func:`~torchevtrack.reference.warp_canvas`), evaluated on the fly
    at the observed pixels only (compiled; module docstring, item 6).

    Args:
        coef: ``(B, N + 6, N + 6)`` B-spline coefficients of the render's template (:func:`_spline_prefilter`),
            zero-padded by 3 pixels (:attr:`TemplateModel.coef`).
        depth: ``(B, N, N)`` canvas depth of the render, background filled (metres, all positive).
        K: ``(B, 4)`` canvas intrinsics; render_pose, pose: ``(B, 7)``.
        obs: ``(B, N * N)`` observation in the canvas.

    Shape: returns a :class:`QuadraticScore` centred at ``pose`` (float64).
    """
    B = coef.shape[0]
    pose = pose.double()
    s0, g, M = torch.empty(B, dtype=torch.float64), torch.empty(B, 6, dtype=torch.float64), \
        torch.empty(B, 6, 6, dtype=torch.float64)
    _quadratic_kernel(_np(coef), _np(depth), _np(K.double()), _np(render_pose.double()), _np(pose), _np(obs),
                      s0.numpy(), g.numpy(), M.numpy())
    return QuadraticScore(pose, s0, g, M)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


class QuadraticScore(NamedTuple):
    """Second-order model of the template score around a reference pose (:meth:`TemplateModel.fit`).

    ``S(delta) = s0 - g . delta + delta^T M delta / 2`` with ``delta = [t - t_ref, log(q q_ref^-1)]``.

    Attributes:
        pose: ``(B, 7)`` float64 reference pose (the model's centre).
        s0: ``(B,)`` score of the reference pose; g: ``(B, 6)``; M: ``(B, 6, 6)`` symmetric.
    """

    pose: torch.Tensor
    s0: torch.Tensor
    g: torch.Tensor
    M: torch.Tensor

    def evaluate(self, poses: torch.Tensor) -> torch.Tensor:
        """Model scores of poses. Shape: ``(B, P, 7) -> (B, P)`` float64."""
        return self.at_steps(pose_delta(self.pose, poses))

    def at_steps(self, delta: torch.Tensor) -> torch.Tensor:
        """Model scores of steps ``delta`` from the reference pose. Shape: ``(B, P, 6) -> (B, P)`` float64."""
        d = delta.double()
        return self.s0[:, None] + ((0.5 * (d @ self.M) - self.g[:, None]) * d).sum(-1)

    def scores(self, pose: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """Model scores of the hypotheses ``steps`` around ``pose``. Shape: ``(B, 7), (B, K, 6) -> (B, K)``."""
        return self.evaluate(apply_steps(pose.double(), steps))


def pose_delta(ref: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Step ``[t - t_ref, log(q q_ref^-1)]`` from ``ref`` to each pose (inverse of :func:`apply_steps`).

    Shape: ``(B, 7), (B, P, 7) -> (B, P, 6)`` float64.
    """
    ref, poses = ref.double(), poses.double()
    rot = quat_log(quat_mul(poses[..., 3:], quat_conj(ref[:, None, 3:]).expand_as(poses[..., 3:])))
    return torch.cat((poses[..., :3] - ref[:, None, :3], rot), -1)


class TemplateModel(NamedTuple):
    """One render's template and its per-pixel score terms around a centre pose (:func:`template_model`).

    Reusable across observations and nearby poses: :meth:`fit` contracts the per-pixel terms with an
    observation into a :class:`QuadraticScore` (microseconds per pose afterwards); :meth:`at` moves the
    centre to another pose by warping the render's template (one exact warp instead of a render);
    :meth:`shift_px` tells how far (image pixels) a pose is from the render's pose.

    Attributes:
        pose: ``(B, 7)`` float64 centre pose of the terms below (the render's pose, or see :meth:`at`).
        render_pose: ``(B, 7)`` float64 pose of the render.
        box: ``(B, 3)`` canvas region ``[cu, cv, side]``, frame pixels; K: ``(B, 4)`` canvas intrinsics.
        gain: ``(B,)`` :func:`~torchevtrack.reference.radial_gain` of the render (sets the z step).
        render_template: ``(B, N, N)`` template (scaled DoG) of the render.
        depth: ``(B, N, N)`` canvas depth of the render, background filled (:func:`~torchevtrack.reference._fill_depth`).
        coef: ``(B, N + 6, N + 6)`` cubic B-spline coefficients of ``render_template`` (the warp's interpolant),
            zero-padded by 3 pixels (the taps of a point up to 2 pixels outside the canvas).
        points: ``(B, P, 3)`` object points of the render (camera frame, metres); valid: ``(B, P)`` bool.
        interior: ``(B,)`` float64 weight of the object's coverage in the template (:func:`template_model`); every
            search of the model pays the matching area term (:func:`newton_kernel`).
    """

    pose: torch.Tensor
    render_pose: torch.Tensor
    box: torch.Tensor
    K: torch.Tensor
    gain: torch.Tensor
    render_template: torch.Tensor
    depth: torch.Tensor
    coef: torch.Tensor
    points: torch.Tensor
    valid: torch.Tensor
    interior: torch.Tensor

    def observe(self, observation: torch.Tensor, observation_origin=(0, 0)) -> torch.Tensor:
        """Observation ``(B, H, W)`` (top-left pixel at ``observation_origin``) resampled into the canvas, ``(B, N * N)``."""
        B, N, _ = self.depth.shape
        obs = check_images(observation, "observation")
        if obs.shape[0] != B:
            raise ValueError(f"observation must have one image per pose ({B}), got {tuple(obs.shape)}")
        return to_canvas(obs.to(self.depth.dtype), self.box, N, observation_origin).reshape(B, N * N)

    def fit(self, observation: torch.Tensor, observation_origin=(0, 0)) -> QuadraticScore:
        """Second-order score model for an observation ``(B, H, W)`` whose top-left pixel is ``observation_origin``."""
        return self.fit_canvas(self.observe(observation, observation_origin))

    def fit_canvas(self, obs: torch.Tensor) -> QuadraticScore:
        """:meth:`fit` for an observation already in the canvas (:meth:`observe`), ``(B, N * N)``."""
        return quadratic_score(self.coef, self.depth, self.K, self.render_pose, self.pose, obs)

    def at(self, pose: torch.Tensor) -> "TemplateModel":
        """The model centred at ``pose`` ``(B, 7)`` (the render's template warped there when it is fitted)."""
        return self._replace(pose=pose.double())

    def shift_px(self, pose: torch.Tensor) -> torch.Tensor:
        """Largest image motion (frame pixels) of the render's object points from the render's pose to ``pose``.

        Shape: ``(B, 7) -> (B,)``; 0 without object pixels.
        """
        d = pose_delta(self.render_pose, pose.double()[:, None])[:, 0]
        X = self.points.double()
        t0 = self.render_pose[:, None, :3]
        moved = quat_rotate(quat_exp(d[:, None, 3:]).expand(*X.shape[:2], 4), X - t0) + t0 + d[:, None, :3]
        f = self.K[:, None, :2].double()
        shift = (f * (moved[..., :2] / moved[..., 2:] - X[..., :2] / X[..., 2:])).norm(dim=-1)
        shift = shift * (self.box[:, 2:].double() / self.depth.shape[-1])  # canvas -> frame pixels
        return torch.where(self.valid, shift, torch.zeros_like(shift)).amax(1)


@kernel(fastmath=EXACT_FASTMATH)
def _taps_pass(src, k, step, dst):
    """``dst[q] = sum_i k[i] src[q + i step]`` (flat arrays), the taps added in order (up to four per pass)."""
    L, n4 = len(dst), (len(k) - 1) // 4 * 4
    a, w = src[:L], k[0]
    for q in range(L):
        dst[q] = w * a[q]
    for i in range(1, n4 + 1, 4):
        a, b = src[i * step:i * step + L], src[(i + 1) * step:(i + 1) * step + L]
        c, d = src[(i + 2) * step:(i + 2) * step + L], src[(i + 3) * step:(i + 3) * step + L]
        w0, w1, w2, w3 = k[i], k[i + 1], k[i + 2], k[i + 3]
        for q in range(L):
            dst[q] = dst[q] + w0 * a[q] + w1 * b[q] + w2 * c[q] + w3 * d[q]
    for i in range(n4 + 1, len(k)):
        a, w = src[i * step:i * step + L], k[i]
        for q in range(L):
            dst[q] += w * a[q]


@kernel
def _blur(x, k, tmp, out):
    """Blur by the 1-D kernel ``k`` along both axes, zero outside: ``x`` is the ``(n, m)`` image zero-padded by
    ``p >= len(k) // 2`` on each side, ``tmp`` and ``out`` are ``(n, m + 2p)``; ``out[:, p:p + m]`` is the blur."""
    n, W = tmp.shape
    p, r = (x.shape[0] - n) // 2, len(k) // 2
    xf, t = x.reshape(-1), tmp.reshape(-1)
    _taps_pass(xf[(p - r) * W:], k, W, t)  # along the columns
    _taps_pass(t[p - r:], k, np.int64(1), out.reshape(-1)[p:n * W - p])  # along the rows (the pads keep rows apart)


@kernel(fastmath=EXACT_FASTMATH)
def _sobel2(a, b, c, u0, u, u1):
    """``|Sobel|^2`` (unnormalised) at column ``u`` of rows ``a, b, c`` with neighbour columns ``u0, u1``."""
    gu = (a[u1] - a[u0]) + 2 * (b[u1] - b[u0]) + (c[u1] - c[u0])
    gv = (c[u0] - a[u0]) + 2 * (c[u] - a[u]) + (c[u1] - a[u1])
    return gu * gu + gv * gv


@kernel(fastmath=EXACT_FASTMATH)
def _edges(x, y, scale, E):
    """``E[p:p + N, p:p + M] = min(sqrt(max(|Sobel x|^2, |Sobel y|^2)) * scale, 1)`` (replicated border, the
    squares rounded to float32) with ``p`` the padding of ``E``."""
    N, M = x.shape
    p = (E.shape[0] - N) // 2
    one = np.float32(1.0)
    for v in range(N):
        v0, v1 = max(v - 1, 0), min(v + 1, N - 1)
        xa, xb, xc, ya, yb, yc, e = x[v0], x[v], x[v1], y[v0], y[v], y[v1], E[v + p, p:]
        for u in range(M - 2):  # the interior, with u + 1 the pixel
            g = np.float32(max(_sobel2(xa, xb, xc, u, u + 1, u + 2), _sobel2(ya, yb, yc, u, u + 1, u + 2)))
            e[u + 1] = min(np.sqrt(g) * scale, one)
        for u, u0, u1 in ((0, 0, 1), (M - 1, M - 2, M - 1)):
            g = np.float32(max(_sobel2(xa, xb, xc, u0, u, u1), _sobel2(ya, yb, yc, u0, u, u1)))
            e[u] = min(np.sqrt(g) * scale, one)


@kernel
def box_kernel(depth, origin, cam, margin, box, gain):
    """The first part of :func:`template_model`, unchecked: the object's extent in each window ``depth`` ``(B, h, w)``
    at ``origin`` ``(B, 2)`` float64 (frame pixels; ``cam`` from :func:`camera_array`, ``margin`` pixels) gives the
    canvas ``box`` ``(B, 3)`` float64 ``[cu, cv, side]`` (:func:`~torchevtrack.reference.canvas_box`) and the ``gain``
    ``(B,)`` (:func:`~torchevtrack.reference.radial_gain`), both written; :func:`model_kernel` makes the rest in that
    box."""
    B, h, w = depth.shape
    cx, cy = cam[2], cam[3]
    for b in range(B):
        ou, ov = origin[b, 0], origin[b, 1]
        umin, umax, vmin, vmax, total, n = window_extent(depth[b], ou, ov, cx, cy, True)
        if n == 0:
            box[b, 0], box[b, 1], box[b, 2] = (w - 1) / 2.0 + ou, (h - 1) / 2.0 + ov, float(max(h, w))
        else:
            box[b, 0], box[b, 1] = (umin + umax) / 2 + ou, (vmin + vmax) / 2 + ov
            box[b, 2] = max(umax - umin, vmax - vmin) + 1 + 2 * margin
        gain[b] = total / max(n, 1.0)


@kernel
def model_kernel(depth, gray, origin, box64, cam, z_fallback, use_gray, use_mask, edge_scale, interior, g1, g2, pre,
                 fill_radius, point_step, box, K, T, coef, Z, points, valid):
    """:func:`template_model` of each window ``depth`` / ``gray`` ``(B, h, w)`` at ``origin`` ``(B, 2)`` float64 in its
    canvas box ``box64`` (:func:`box_kernel`), unchecked, in one pass per element; releases the GIL.

    Inputs besides those: ``cam`` (:func:`camera_array`), ``z_fallback`` ``(B,)`` float64 depth of the background far
    from the object (the pose's ``tz``), ``use_gray`` (else ``gray`` is the depth), ``use_mask`` (the silhouette's
    edges too), ``edge_scale = 0.125 / edge_clip``, ``interior`` (the weight of the object's coverage added to the
    template, :func:`template_model`), the filters ``g1, g2, pre`` of :func:`model_filters`, the
    ``fill_radius`` of the background fill and the ``point_step`` between object points (both ``max(1, N // 16)``).
    Outputs, overwritten: the fields ``box, K, render_template = T, coef, depth = Z, points, valid`` of a
    :class:`TemplateModel` in the render's dtype (``coef`` zeroed beforehand: only its interior is written).

    The box (also into ``box``, in its dtype) gives the canvas intrinsics ``K`` (:func:`canvas_intrinsics`); the
    window resampled into the box (:func:`~torchevtrack.reference.prepare_canvas`) gives the template (Sobel edges, DoG, scale and clip: the
    template of :func:`~torchevtrack.reference.hypothesis_templates`), its B-spline coefficients ``coef`` (zero-padded by 3), the object points
    of every ``point_step``-th canvas pixel and the background-filled depth ``Z`` (:func:`~torchevtrack.reference._fill_depth`).
    """
    B = depth.shape[0]
    N = T.shape[-1]
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    # the canvas images and filters in float32 (twice the SIMD width; the template is float32); p: zero padding of
    # the images that are blurred
    p = max(len(g1), len(g2), len(pre)) // 2
    W = N + 2 * p
    mask, shade = np.empty((N, N), np.float32), np.empty((N, N), np.float32)
    E, Tp = np.zeros((W, W), np.float32), np.zeros((W, W), np.float32)
    tmp, B1, B2 = np.empty((N, W), np.float32), np.empty((N, W), np.float32), np.empty((N, W), np.float32)
    scale = np.float32(edge_scale)
    for b in range(B):
        ou, ov = origin[b, 0], origin[b, 1]
        cu, cv, side = box64[b, 0], box64[b, 1], box64[b, 2]
        box[b, 0], box[b, 1], box[b, 2] = cu, cv, side
        step, half = side / N, N / 2.0 - 0.5
        K[b, 0], K[b, 1], K[b, 2], K[b, 3] = fx / step, fy / step, (cx - cu) / step + half, (cy - cv) / step + half
        _resample(depth[b], gray[b], cu - ou, cv - ov, step, use_gray, Z[b], mask, shade)
        k = 0
        for i in range(point_step // 2, N, point_step):
            for j in range(point_step // 2, N, point_step):
                z = Z[b, i, j]
                points[b, k, 0], points[b, k, 1], points[b, k, 2] = (j - K[b, 2]) / K[b, 0] * z, (i - K[b, 3]) / K[b, 1] * z, z
                valid[b, k] = z > 0
                k += 1
        _edges(shade if use_gray else mask, mask if use_mask else shade, scale, E)
        _blur(E, g1, tmp, B1)
        _blur(E, g2, tmp, B2)  # Difference of Gaussians B1 - B2
        _dog_template(B1, B2, T[b], Tp)
        if interior != 0.0:
            _add_interior(mask, np.float32(interior), T[b], Tp)
        _blur(Tp, pre, tmp, B1)
        coef[b, 3:N + 3, 3:N + 3] = B1[:, p:p + N]  # the B-spline coefficients
        fill_kernel(Z[b], z_fallback[b], fill_radius)


@kernel
def _add_interior(mask, c, T, Tp):
    """``T += c * mask`` and the same into the zero-padded copy ``Tp`` (the object's coverage of each canvas pixel)."""
    N = T.shape[0]
    p = (Tp.shape[0] - N) // 2
    for v in range(N):
        for u in range(N):
            T[v, u] += c * mask[v, u]
            Tp[v + p, u + p] += c * mask[v, u]


@kernel(fastmath=EXACT_FASTMATH)
def _dog_template(B1, B2, T, Tp):
    """``T = clip(D * 0.5 / max|D|, -0.5, 0.5)`` of the Difference of Gaussians ``D = B1 - B2`` (into ``B1``), also
    into ``Tp`` (``T`` zero-padded by ``p``); ``B1``, ``B2`` are :func:`_blur` outputs ``(N, N + 2p)``."""
    N = T.shape[0]
    p = (Tp.shape[0] - N) // 2
    peak = np.zeros(N, np.float32)  # of each column: an element-wise max vectorises, a max reduction does not
    for v in range(N):
        d, e = B1[v, p:p + N], B2[v, p:p + N]
        for u in range(N):
            d[u] -= e[u]
            peak[u] = max(peak[u], abs(d[u]))
    s = np.float32(0.5 / max(peak.max(), 1e-12))
    for v in range(N):
        d, t, tp = B1[v, p:p + N], T[v], Tp[v + p, p:p + N]
        for u in range(N):
            t[u] = tp[u] = min(max(d[u] * s, np.float32(-0.5)), np.float32(0.5))


@kernel
def _resample(depth, gray, cu, cv, step, use_gray, c_depth, c_mask, c_gray):
    """:func:`to_canvas` of one window (box centre ``(cu, cv)`` in window pixels, ``step`` window pixels per canvas
    pixel): the object depth (depth-weighted over the object taps only), the mask and, if ``use_gray``, the grey.
    Bilinear as two linear passes per canvas row: between two window rows, then along the row."""
    h, w = depth.shape
    N = c_depth.shape[0]
    c0, c1, a0, a1 = canvas_taps(cu, step, N, w)
    r0, r1, b0, b1 = canvas_taps(cv, step, N, h)
    lo, hi = c0[0], c1[N - 1] + 1  # the window columns the canvas samples
    c0 -= lo
    c1 -= lo
    V = np.zeros((3, hi - lo))  # object depth times object weight, object weight, grey of one canvas row
    vd, vm, vg = V[0], V[1], V[2]
    sd, sm = np.empty(N), np.empty(N)
    for i in range(N):
        ws, wt = b0[i], b1[i]
        zs, zt = depth[r0[i], lo:hi], depth[r1[i], lo:hi]
        for u in range(hi - lo):
            z0, z1 = zs[u], zt[u]
            m0, m1 = ws if z0 > 0 else 0.0, wt if z1 > 0 else 0.0
            vd[u], vm[u] = m0 * z0 + m1 * z1, m0 + m1
        if use_gray:
            gs, gt = gray[r0[i], lo:hi], gray[r1[i], lo:hi]
            for u in range(hi - lo):
                vg[u] = ws * gs[u] + wt * gt[u]
        for j in range(N):  # along the row (gathers)
            sd[j], sm[j] = a0[j] * vd[c0[j]] + a1[j] * vd[c1[j]], a0[j] * vm[c0[j]] + a1[j] * vm[c1[j]]
            c_gray[i, j] = a0[j] * vg[c0[j]] + a1[j] * vg[c1[j]]
        for j in range(N):  # a loop of its own, vectorised
            c_mask[i, j] = sm[j]
            c_depth[i, j] = sd[j] / sm[j] if sm[j] > 1e-6 else 0.0


@functools.lru_cache(maxsize=8)
def model_filters(canvas: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The DoG's two Gaussians and the B-spline prefilter of a canvas size, the ``g1, g2, pre`` of
    :func:`model_kernel`: three 1-D float32 arrays (cached constants, never modified)."""
    f32 = torch.float32
    return (gaussian_taps(odd_size(canvas / 20), f32).numpy(), gaussian_taps(odd_size(canvas / 8), f32).numpy(),
            prefilter_taps(f32).numpy())


def template_model(
    pose: torch.Tensor,
    depth: torch.Tensor,
    gray: torch.Tensor | None,
    origin,
    camera: Camera,
    *,
    canvas: int = 128,
    margin_px: float = 20.0,
    edge_clip: float = 0.1,
    silhouette: bool = True,
    interior: float = 0.0,
) -> TemplateModel:
    """Build the :class:`TemplateModel` of a render (window at ``origin``) made at ``pose``, in one compiled call.

    ``interior`` adds the object's coverage of each canvas pixel, times ``interior``, to the template (the module
    docstring's item 2): the score then also counts the events on the object, which a printed texture the mesh does
    not have puts there, so that they pull the outline no more inwards than outwards; the Newton search pays for the
    area the object covers (:func:`newton_kernel`). ``0`` is the edge template alone.

    Shape: ``(B, 7), (B, h, w), (B, h, w) or None, (B, 2) -> TemplateModel`` with ``N = canvas``.
    """
    if gray is None and not silhouette:
        raise ValueError("without a grey render the template needs silhouette=True")
    if not edge_clip > 0:
        raise ValueError(f"edge_clip must be positive, got {edge_clip}")
    if not (math.isfinite(interior) and interior >= 0):
        raise ValueError(f"interior must be finite and >= 0, got {interior}")
    depth = check_images(depth, "depth")
    B, dt = pose.shape[0], depth.dtype
    d, cam = depth.detach().numpy(), camera_array(camera)
    o = batch_origin(origin, B, torch.float64).contiguous().numpy()
    box, gain = render_box(d, o, cam, margin_px)
    return model_in_box(pose.detach().double().numpy(), d, (depth if gray is None else gray.to(dt)).detach().numpy(),
                        gray is not None, o, cam, box, gain, canvas, edge_clip, silhouette, interior)


def camera_array(camera: Camera) -> np.ndarray:
    """``[fx, fy, cx, cy]`` float64, the ``cam`` argument of the compiled template kernels.

    Shape: ``(4,)``.
    """
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy])


def render_box(depth: np.ndarray, origin: np.ndarray, cam: np.ndarray,
               margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The first part of :func:`template_model` on numpy arrays, unchecked (:func:`box_kernel`): the canvas box
    ``(B, 3)`` float64 and the gain ``(B,)`` in the render's dtype, of renders ``depth`` ``(B, h, w)`` at ``origin``
    ``(B, 2)`` float64, ``cam`` from :func:`camera_array`. The observation needs only the box: the model can follow
    (:func:`model_in_box`)."""
    box, gain = np.empty((len(depth), 3)), np.empty(len(depth), dtype=depth.dtype)
    box_kernel(depth, origin, cam, float(margin_px), box, gain)
    return box, gain


def model_in_box(pose: np.ndarray, depth: np.ndarray, shade: np.ndarray, use_gray: bool, origin: np.ndarray,
                 cam: np.ndarray, box64: np.ndarray, gain: np.ndarray, N: int, edge_clip: float,
                 silhouette: bool, interior: float = 0.0) -> TemplateModel:
    """The rest of :func:`template_model` in the canvas box of :func:`render_box` (:func:`model_kernel`), on numpy
    arrays, unchecked: ``pose`` ``(B, 7)`` float64 is the render's, ``depth`` ``(B, h, w)`` at ``origin`` ``(B, 2)``
    float64 the render, ``shade`` the grey render (or the depth when ``use_gray`` is false), ``box64`` and ``gain``
    :func:`render_box`'s, ``N`` the canvas side; ``edge_clip``, ``silhouette`` and ``interior`` as for
    :func:`template_model`.

    Shape: returns the :class:`TemplateModel` (tensors sharing the new arrays, in the render's dtype).
    """
    B, dt = len(depth), depth.dtype
    step = max(1, N // 16)  # object points for shift_px: every step-th canvas pixel
    P = len(range(step // 2, N, step)) ** 2
    box, K = np.empty((B, 3), dt), np.empty((B, 4), dt)
    T, Z, coef = np.empty((B, N, N), dt), np.empty((B, N, N), dt), np.zeros((B, N + 6, N + 6), dt)
    points, valid = np.empty((B, P, 3), dt), np.empty((B, P), dtype=np.bool_)
    model_kernel(depth, shade, origin, box64, cam, np.ascontiguousarray(pose[:, 2]), use_gray, silhouette,
                 0.125 / edge_clip, float(interior), *model_filters(N), step, step, box, K, T, coef, Z, points, valid)
    pose = torch.from_numpy(pose)
    return TemplateModel(pose, pose, *(torch.from_numpy(a) for a in (box, K, gain, T, Z, coef, points, valid)),
                         torch.full((B,), float(interior), dtype=torch.float64))


# -- the stage --------------------------------------------------------------------------------
def check_options(rule, iterations, max_dz=math.inf) -> None:
    """A one-line ``ValueError`` unless ``rule`` is one of ``RULES``, ``iterations`` an integer >= 1 and ``max_dz``
    positive (metres; ``inf``: no bound)."""
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    if isinstance(max_dz, bool) or not isinstance(max_dz, (int, float)) or not max_dz > 0:
        raise ValueError(f"max_dz must be a positive number of metres (inf: no bound), got {max_dz!r}")


def correct_canvas(
    model: TemplateModel,
    pose: torch.Tensor,
    obs: torch.Tensor,
    camera: Camera,
    *,
    dp_px: float = 1.0,
    dtheta_deg: float = 0.5,
    rule: str = "newton",
    iterations: int = 1,
    max_dz: float = math.inf,
    z_ref: torch.Tensor | None = None,
) -> Correction:
    """Correct poses near a render's with its :class:`TemplateModel` against an observation already in the model's
    canvas (:meth:`TemplateModel.observe`, or :func:`torchevtrack.stages.eros.canvas_observation` of ``model.box``).

    Every iteration fits the model at its current pose (the render's template warped there), so ``pose`` may differ
    from the render's pose (reuse of an earlier render); keep ``model.shift_px(pose)`` small, as the warp approximates
    a render for small motions only. ``rule="newton"`` runs :func:`newton_search` (compiled); the paper's ``"argmax"``
    and EDOPT's ``"group"`` (the ablation switch ``template.rule``) run the torch search of
    :func:`torchevtrack.reference.rule_search`. The returned pose has ``pose``'s dtype, the scores the render's.

    Args:
        dp_px, dtheta_deg: translation step (image pixels) and rotation step (degrees) of the hypotheses (module
            docstring, item 3); rule: ``"newton"``, ``"argmax"`` or ``"group"`` (item 5); iterations: maximum
            corrections, repeated while the score keeps improving. Every rule's scores pay the area term of the
            model's ``interior`` (:func:`newton_kernel`). max_dz, z_ref: the corrected poses' depths stay within
            ``max_dz`` metres of ``z_ref`` ``(B,)`` (metres; ``None``: ``pose``'s depths): each step's depth is
            clipped to the band, the other axes searched at the clipped depth (``inf``: no bound).

    Shape: ``TemplateModel, (B, 7), (B, N, N) or (B, N * N)[, (B,)] -> Correction``.
    """
    pose = check_poses(pose, "pose")
    check_options(rule, iterations, max_dz)
    B, N = model.pose.shape[0], model.depth.shape[-1]
    if pose.shape[0] != B:
        raise ValueError(f"pose must have one row per model element ({B}), got {tuple(pose.shape)}")
    if obs.shape not in ((B, N, N), (B, N * N)):
        raise ValueError(f"obs must be the ({B}, {N}, {N}) canvas observation, got {tuple(obs.shape)}")
    obs = obs.reshape(B, N * N)
    if z_ref is not None and (not isinstance(z_ref, torch.Tensor) or z_ref.shape != (B,)
                              or not bool(torch.isfinite(z_ref).all())):
        raise ValueError(f"z_ref must be a finite ({B},) tensor of depths (metres)")
    if rule == "newton":
        return newton_search(model, pose, obs, camera, dp_px=dp_px, dtheta_deg=dtheta_deg, iterations=iterations,
                             max_dz=max_dz, z_ref=z_ref)
    from torchevtrack.reference import rule_search  # the ablation switch (reference imports this module)

    return rule_search(model, pose, obs, camera, dp_px=dp_px, dtheta_deg=dtheta_deg, rule=rule, iterations=iterations,
                       max_dz=max_dz, z_ref=z_ref)


def newton_arrays(model: TemplateModel, pose: np.ndarray, obs: np.ndarray, fx: float, fy: float, dp: float,
                  dtheta: float, iterations: int, max_dz: float = math.inf,
                  z_ref: np.ndarray | None = None) -> Correction:
    """The compiled Newton search of :func:`newton_search` on numpy arrays (the tracker's hot path calls this).

    Args:
        model: the render's :class:`TemplateModel`; pose: ``(B, 7)`` float64 start poses; obs: ``(B, N, N)`` or
            ``(B, N * N)`` observation in the canvas; fx, fy: the frame's focal lengths (px); dp: the image step
            (px); dtheta: the rotation step (radians); iterations: the maximum number of Newton rounds (the area
            term of the model's ``interior`` included); max_dz, z_ref: the depths stay within ``max_dz`` metres of
            ``z_ref`` ``(B,)`` float64 (``None``: ``pose``'s depths).
    Returns: a :class:`Correction` of numpy arrays: ``pose`` ``(B, 7)`` float64, ``score`` ``(B,)`` and ``scores``
        ``(B, 13)`` in the model's dtype, ``index`` (the first of ties, as torch's ``argmax``), ``applied`` all false
        (the step is not one of the hypotheses) and ``iterations`` ``(B,)`` int64 (the rounds that moved).
    """
    B = pose.shape[0]
    out = np.empty((B, 7))
    score, scores, moved = np.empty(B), np.empty((B, NUM_HYPOTHESES)), np.empty(B, dtype=np.int64)
    newton_kernel(_np(model.coef), _np(model.depth), _np(model.K).astype(np.float64, copy=False),
                  _np(model.render_pose), np.ascontiguousarray(pose, dtype=np.float64), obs.reshape(B, -1),
                  _np(model.gain).astype(np.float64, copy=False), float(fx), float(fy), float(dp), float(dtheta),
                  int(iterations), NEWTON_DAMPING, NEWTON_MAX_STEP, float(max_dz),
                  np.ascontiguousarray(pose[:, 2] if z_ref is None else z_ref, dtype=np.float64), _np(model.valid),
                  _np(model.interior), out, score, scores, moved)
    dtype = _np(model.depth).dtype
    scores = scores.astype(dtype)
    return Correction(out, score.astype(dtype), scores, scores.argmax(1),
                      np.zeros((B, NUM_HYPOTHESES), dtype=np.bool_), moved)


def newton_search(model: TemplateModel, pose: torch.Tensor, obs: torch.Tensor, camera: Camera, *,
                  dp_px: float = 1.0, dtheta_deg: float = 0.5, iterations: int = 1,
                  max_dz: float = math.inf, z_ref: torch.Tensor | None = None) -> Correction:
    """The ``"newton"`` rule's search on the model's exact quadratic, compiled in one call (the tracker's).

    The same search as :func:`~torchevtrack.reference.search` with ``rule="newton"`` and the scorer of
    :func:`~torchevtrack.reference.rule_search` (the quadratic model refitted at every iteration's pose, the damped
    Newton step of :func:`~torchevtrack.reference.newton_step` with ``NEWTON_DAMPING`` and ``NEWTON_MAX_STEP``,
    stopping when a step does not raise the score), but the model's ``g`` and ``M`` give the step directly (the
    28-score fit of the torch step recovers them exactly) and everything runs in float64, without per-iteration
    tensors. :func:`newton_arrays` is the same search on numpy arrays.

    Args:
        model: the render's :class:`TemplateModel`; pose: ``(B, 7)`` start poses; obs: ``(B, N * N)``
            observation in the canvas (:meth:`TemplateModel.observe`).
        dp_px, dtheta_deg, iterations, max_dz, z_ref: see :func:`correct_canvas`.

    Shape: ``(B, 7), (B, N * N)[, (B,)] -> Correction`` (``applied`` all false: the step is not one of the hypotheses).
    """
    c = newton_arrays(model, _np(pose.double()), _np(obs), camera.fx, camera.fy, dp_px, math.radians(dtheta_deg),
                      iterations, max_dz, None if z_ref is None else _np(z_ref.double()))
    return Correction(torch.from_numpy(c.pose).to(pose.dtype), *(torch.from_numpy(f) for f in c[1:]))


class TemplateCorrector(nn.Module):
    """Stage 5, local template correction of propagated poses: the template of one render matched against the
    observation (module docstring), with the options bound to a camera.

    Args:
        camera: the frame camera.
        canvas: canvas size in pixels (100..150 in the paper); margin_px: margin around the object's bounding box,
            frame pixels; edge_clip: Sobel magnitude at which edges saturate; silhouette: add the mask's edges to
            the grey edges; interior: weight of the object's coverage in the template (:func:`template_model`).
        dp_px, dtheta_deg, rule, iterations: see :func:`correct_canvas`.
        (Defaults: the config section ``template``, :class:`~torchevtrack.config.TemplateConfig`.)

    Calls:
        ``forward(pose, depth, gray, origin, observation, observation_origin=(0, 0)) -> Correction``: the render
        ``depth`` (metres, 0 = background) and ``gray`` (``[0, 1]``, or ``None``: silhouette edges only) of the window
        at ``origin`` made at ``pose``, against ``observation`` (median-blurred EROS, top-left frame pixel
        ``observation_origin``). To reuse one render over several updates, ``model = template_model(pose, depth,
        gray, origin)`` once, then ``correct_model(model, pose, observation, observation_origin)`` (or
        ``correct_canvas(model, pose, obs)`` with the observation already in the model's canvas) while
        ``model.shift_px(pose)`` stays below about a pixel.

    Shape: ``(B, 7) float, (B, h, w), (B, h, w) or None, (B, 2) or (2,), (B, H, W) -> Correction`` of ``B`` poses;
    poses in metres and unit quaternions, depth in metres (0 = background), observation in ``[0, 1]``.

    Example:
        >>> from torchevtrack.camera import Camera
        >>> TemplateCorrector(Camera(64, 64, 80.0, 80.0, 31.5, 31.5)).options["rule"]
        'newton'
    """

    def __init__(
        self,
        camera: Camera,
        canvas: int = TemplateConfig.canvas,
        margin_px: float = TemplateConfig.margin_px,
        dp_px: float = TemplateConfig.dp_px,
        dtheta_deg: float = TemplateConfig.dtheta_deg,
        rule: str = TemplateConfig.rule,
        iterations: int = TemplateConfig.iterations,
        edge_clip: float = 0.1,
        silhouette: bool = True,
        interior: float = TemplateConfig.interior,
    ) -> None:
        super().__init__()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a torchevtrack Camera, got {type(camera).__name__}")
        check_options(rule, iterations)
        if not (dp_px > 0 and dtheta_deg > 0 and margin_px >= 0 and edge_clip > 0):
            raise ValueError("dp_px, dtheta_deg and edge_clip must be positive and margin_px non-negative")
        if not (math.isfinite(interior) and interior >= 0):
            raise ValueError(f"interior must be finite and >= 0, got {interior}")
        self.camera = camera
        self.options = dict(
            canvas=canvas, margin_px=margin_px, dp_px=dp_px, dtheta_deg=dtheta_deg, rule=rule,
            iterations=iterations, edge_clip=edge_clip, silhouette=silhouette, interior=interior,
        )

    @classmethod
    def from_config(cls, camera: Camera, cfg: TemplateConfig) -> "TemplateCorrector":
        """The correction of the config section ``template`` (:class:`~torchevtrack.config.TemplateConfig`; its
        ``max_depth_speed`` is the tracker's, which knows the period: :func:`correct_canvas`'s ``max_dz``)."""
        return cls(camera, canvas=cfg.canvas, margin_px=cfg.margin_px, dp_px=cfg.dp_px, dtheta_deg=cfg.dtheta_deg,
                   rule=cfg.rule, iterations=cfg.iterations, interior=cfg.interior)

    def forward(self, pose, depth, gray, origin, observation, observation_origin=(0, 0)) -> Correction:
        check_correct(pose, depth, gray, observation, **self.options)
        return self.correct_model(self.template_model(pose, depth, gray, origin), pose, observation, observation_origin)

    def template_model(self, pose, depth, gray, origin) -> TemplateModel:
        """:func:`template_model` of a render (window at ``origin``) made at ``pose``."""
        o = self.options
        return template_model(check_poses(pose, "pose"), check_images(depth, "depth"), gray, origin, self.camera,
                              canvas=o["canvas"], margin_px=o["margin_px"], edge_clip=o["edge_clip"],
                              silhouette=o["silhouette"], interior=o["interior"])

    def correct_model(self, model: TemplateModel, pose, observation, observation_origin=(0, 0)) -> Correction:
        """:meth:`correct_canvas` of the ``observation`` ``(B, H, W)`` (top-left frame pixel ``observation_origin``)
        resampled into the model's canvas."""
        return self.correct_canvas(model, pose, model.observe(observation, observation_origin))

    def correct_canvas(self, model: TemplateModel, pose, obs) -> Correction:
        """:func:`correct_canvas` (the observation already in the model's canvas) with this corrector's options."""
        o = self.options
        return correct_canvas(model, pose, obs, self.camera, dp_px=o["dp_px"], dtheta_deg=o["dtheta_deg"],
                              rule=o["rule"], iterations=o["iterations"])

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.options.items())


# -- input checks -----------------------------------------------------------------------------
def check_correct(pose, depth, gray, observation, *, canvas, rule, iterations, silhouette, **_) -> None:
    """The checks of a correction's inputs and options (:meth:`TemplateCorrector.forward`,
    :func:`~torchevtrack.reference.correct`): a one-line ``TypeError`` / ``ValueError`` for the first problem, else
    ``None``."""
    check_poses(pose, "pose")
    B = check_images(depth, "depth").shape[0]
    if B != pose.shape[0]:
        raise ValueError(f"depth must have one image per pose ({pose.shape[0]}), got {tuple(depth.shape)}")
    if gray is not None:
        if check_images(gray, "gray").shape != depth.shape:
            raise ValueError(f"gray must match depth {tuple(depth.shape)}, got {tuple(gray.shape)}")
    elif not silhouette:
        raise ValueError("without a grey render the template needs silhouette=True")
    if check_images(observation, "observation").shape[0] != B:
        raise ValueError(f"observation must have one image per pose ({B}), got {tuple(observation.shape)}")
    check_options(rule, iterations)
    if isinstance(canvas, bool) or not isinstance(canvas, int) or canvas < 16:
        raise ValueError(f"canvas must be an integer >= 16 pixels, got {canvas!r}")


def check_poses(pose, name: str) -> torch.Tensor:
    """``pose`` if it is a floating-point ``(B, 7)`` tensor with the object in front of the camera, else a one-line
    ``TypeError`` / ``ValueError`` naming ``name``."""
    if not isinstance(pose, torch.Tensor) or not pose.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor (B, 7), got {type(pose).__name__}")
    if pose.ndim != 2 or pose.shape[1] != 7:
        raise ValueError(f"{name} must have shape (B, 7) [tx, ty, tz, qw, qx, qy, qz], got {tuple(pose.shape)}")
    if not bool((pose[:, 2].detach().cpu().numpy() > 0).all()):  # numpy: one small check per call, without torch's dispatch
        raise ValueError(f"{name} places the object behind the camera (tz <= 0)")
    return pose


def check_images(x, name: str) -> torch.Tensor:
    """``x`` if it is a floating-point ``(B, H, W)`` tensor with pixels, else a one-line ``TypeError`` /
    ``ValueError`` naming ``name``."""
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor (B, H, W), got {type(x).__name__}")
    if x.ndim != 3 or x.shape[1] == 0 or x.shape[2] == 0:
        raise ValueError(f"{name} must have shape (B, H, W), got {tuple(x.shape)}")
    return x


def batch_origin(origin, B: int, dtype: torch.dtype) -> torch.Tensor:
    """A window origin ``(u0, v0)`` or ``(B, 2)`` as a ``(B, 2)`` tensor of ``dtype`` (one-line ``ValueError`` for
    another shape)."""
    o = torch.as_tensor(origin, dtype=dtype)
    if o.shape == (2,):
        o = o.expand(B, 2)
    if o.shape != (B, 2):
        raise ValueError(f"origin must be (u0, v0) or a (B, 2) tensor, got shape {tuple(o.shape)}")
    return o
