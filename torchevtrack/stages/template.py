"""Stage 5: local template correction (EDOPT-style), batched over B and over the 13 hypotheses.

Pipeline of one correction (all batched, no loop over pixels or hypotheses):

1. **Canvas.** The object's pixels in a render at the propagated pose (``depth > 0``; the render may be
   a window of the frame whose top-left pixel is ``origin``) give a bounding box; it is grown by
   ``margin_px``, made square and resampled (bilinear ``grid_sample``) into a ``canvas x canvas``
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
   favoured by its normalisation; zero stays zero) and clipped to ``[-0.5, 0.5]``.
   Score = ``sum(template * observation)`` over the canvas.
3. **Hypotheses** (:func:`hypothesis_steps`): index 0 is the null motion, then ``+/-`` steps along
   ``tx, ty, tz, rx, ry, rz`` (index ``1 + 2 a`` is ``+``, ``2 + 2 a`` is ``-`` for axis ``a``).
   A step ``[dt, phi]`` moves the pose as ``t' = t + dt``, ``q' = exp(phi) (x) q``: a translation
   in the camera frame, or a rotation about a **camera** axis through the **object origin** (the
   rotation is applied on the left, as everywhere in :mod:`torchevtrack.geometry`). Names:
   pitch = ``rx``, yaw = ``ry``, roll = ``rz`` (the optical axis). Step sizes (paper Eqs. 10-11,
   object motion, so ``+x`` moves the image by ``+dp``): ``dx = z dp / fx``, ``dy = z dp / fy``,
   ``dz = dp / mean_i(|(u_i - cx, v_i - cy)| / Z_i)`` over the object's pixels (Eq. 10 with the
   per-pixel depth ``Z_i``; for a fronto-parallel object it is ``z dp / pbar``), rotations
   ``dtheta``.
4. **Warp** (:func:`warp_canvas`): one render gives all 13 templates. For each canvas pixel ``q`` of a
   hypothesis image, ``q`` is back-projected with the *base* depth at ``q``, moved by the inverse of
   the hypothesis' rigid motion ``T_h T_0^-1`` and projected: that is where ``q``'s content came from
   (inverse warp, ``grid_sample``). Using the base depth instead of the (unknown) hypothesis
   depth at ``q`` is the negated-forward-flow approximation: the position error is second order,
   about ``|flow| * |grad flow|`` (below 0.01 px for one-pixel steps inside a surface). Background
   pixels take the mean object depth of their neighbourhood (radius ``canvas / 16``) or the pose's
   depth, so silhouettes and their negative band move with the object. Disocclusions of a 0.5 deg
   rotation are not modelled. Sampling is **cubic B-spline** interpolation (prefiltered, evaluated
   with four bilinear fetches): the null hypothesis samples the base exactly while a step samples
   between canvas pixels, so the interpolator must neither blur nor sharpen. Bilinear blurs a
   sub-pixel sample by a few % of the peak and biased every score toward the null (in development it
   lost all 12 one-step offsets of a rendered box to the null); torch's bicubic (``a = -0.75``)
   sharpens by about 1 %, which let 0.5 deg rotations beat the null on an observation at the null
   pose. The B-spline is flat to ~1e-4 in the band of the template. By default
   (``warp="template"``) the finished template (DoG output) is warped: Sobel and DoG then run once
   per batch element instead of 13 times, and interpolating the smooth DoG is more accurate than
   interpolating the sharp grey image (measured against re-rendered templates). The DoG is
   isotropic, so it commutes exactly with the translation and roll warps and up to the scale change
   (``dp / pbar``, ~1 %) with the others. ``warp="image"`` warps grey and mask and filters each
   hypothesis instead.
5. **Update** (:func:`select`): ``"argmax"`` (the paper) applies the best of the 13 (the null wins
   ties). ``"group"`` (EDOPT) takes, in each group ``{tx, ry}, {ty, rx}, {rz}, {tz}``, the best of its
   hypotheses and applies it if it beats the null score; the applied steps are composed in that group
   order (translations add, rotations ``exp(phi_4) ... exp(phi_1) (x) q``). With ``iterations > 1``
   the correction repeats around the new pose while the score of the corrected pose keeps improving,
   re-warping the same render (a first-order warp, accurate for a few pixels of cumulative motion).

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
    >>> out = TemplateCorrector(cam, canvas=64, margin_px=8)(pose, depth, None, (0, 0), obs)
    >>> int(out.index), round(float(out.pose[0, 0]) * 80 / 0.5, 2)  # +x hypothesis: 1 px right
    (1, 1.0)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, spatial_gradient
from torch import nn

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_canonical, quat_exp, quat_mul, quat_to_matrix

__all__ = [
    "AXES",
    "GROUPS",
    "NUM_HYPOTHESES",
    "Correction",
    "render_window",
    "canvas_box",
    "canvas_intrinsics",
    "to_canvas",
    "edge_map",
    "dog",
    "radial_gain",
    "hypothesis_steps",
    "apply_steps",
    "warp_canvas",
    "CanvasRender",
    "prepare_canvas",
    "hypothesis_templates",
    "score",
    "select",
    "correct",
    "TemplateCorrector",
]

AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
NUM_HYPOTHESES = 1 + 2 * len(AXES)
# EDOPT's groups of axes whose image motions look alike, as axis indices into AXES.
GROUPS = ((0, 4), (1, 3), (5,), (2,))


class Correction(NamedTuple):
    """Result of :func:`correct`.

    Attributes:
        pose: ``(B, 7)`` corrected pose.
        score: ``(B,)`` template score of the corrected pose.
        scores: ``(B, 13)`` scores of the hypotheses around the input pose (first iteration).
        index: ``(B,)`` int64, best of those 13 (0 = null).
        applied: ``(B, 13)`` bool, hypotheses applied in the first iteration (one-hot or none for
            ``"argmax"``; up to one per group for ``"group"``).
        iterations: ``(B,)`` int64, number of iterations that moved the pose.
    """

    pose: torch.Tensor
    score: torch.Tensor
    scores: torch.Tensor
    index: torch.Tensor
    applied: torch.Tensor
    iterations: torch.Tensor


# -- regions ----------------------------------------------------------------------------------
def render_window(pose: torch.Tensor, camera: Camera, radius: float, margin_px: int = 24) -> torch.Tensor:
    """Window ``(u0, v0, w, h)`` of the frame that contains the object, to render only that region.

    The object is bounded by a sphere of ``radius`` metres around the pose origin; the window is the
    square around its projection (conservative: half-size ``f r / (z - r)``) plus ``margin_px``.

    Shape: ``(B, 7) -> (B, 4)`` int64.
    """
    pose = _check_poses(pose, "pose")
    if not radius > 0:
        raise ValueError(f"radius must be positive (metres), got {radius}")
    t = pose[:, :3].double()
    z = t[:, 2].clamp_min(radius * 1.05)
    centre = torch.stack((camera.fx * t[:, 0] / t[:, 2] + camera.cx, camera.fy * t[:, 1] / t[:, 2] + camera.cy), -1)
    half = torch.stack((camera.fx * radius / (z - radius), camera.fy * radius / (z - radius)), -1) + margin_px
    lo = torch.floor(centre - half)
    size = torch.ceil(centre + half) - lo + 1
    return torch.cat((lo, size), -1).long()


def canvas_box(depth: torch.Tensor, origin, margin_px: float = 20.0) -> torch.Tensor:
    """Square region of interest ``[cu, cv, side]`` (frame pixels) around the object in a render.

    The bounding box of the ``depth > 0`` pixels, grown by ``margin_px`` on each side and made square
    about its centre. A render without object pixels gives the window itself (centre, longer side).

    Args:
        depth: ``(B, h, w)`` render (metres, 0 = background) of the window whose top-left pixel is ``origin``.
        origin: ``(B, 2)`` or ``(2,)`` window origin ``(u0, v0)`` in frame pixels.
        margin_px: margin in frame pixels.

    Shape: ``(B, h, w), (B, 2) -> (B, 3)``.
    """
    depth = _check_images(depth, "depth")
    B, h, w = depth.shape
    origin = _origin(origin, B, depth.dtype)
    mask = depth > 0
    cols, rows = mask.any(1), mask.any(2)
    iu = torch.arange(w, dtype=depth.dtype)
    iv = torch.arange(h, dtype=depth.dtype)
    inf = torch.tensor(math.inf, dtype=depth.dtype)
    umin, umax = torch.where(cols, iu, inf).amin(1), torch.where(cols, iu, -inf).amax(1)
    vmin, vmax = torch.where(rows, iv, inf).amin(1), torch.where(rows, iv, -inf).amax(1)
    empty = ~cols.any(1)
    cu = torch.where(empty, (w - 1) / 2.0, (umin + umax) / 2) + origin[:, 0]
    cv = torch.where(empty, (h - 1) / 2.0, (vmin + vmax) / 2) + origin[:, 1]
    side = torch.where(empty, float(max(h, w)), torch.maximum(umax - umin, vmax - vmin) + 1 + 2 * margin_px)
    return torch.stack((cu, cv, side), -1)


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
        box: ``(B, 3)`` ``[cu, cv, side]`` in frame pixels (:func:`canvas_box`).
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
    origin = _origin(origin, B, x.dtype)
    box = box.to(x.dtype)
    offs = (torch.arange(canvas, dtype=x.dtype) + 0.5 - canvas / 2.0) * (box[:, 2:] / canvas)  # (B, N)
    u = box[:, :1] + offs - origin[:, :1]
    v = box[:, 1:2] + offs - origin[:, 1:]
    gx = ((2 * u + 1) / w - 1)[:, None, :].expand(B, canvas, canvas)
    gy = ((2 * v + 1) / h - 1)[:, :, None].expand(B, canvas, canvas)
    out = F.grid_sample(x, torch.stack((gx, gy), -1), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[:, 0] if squeeze else out


# -- templates --------------------------------------------------------------------------------
def edge_map(gray: torch.Tensor | None, mask: torch.Tensor | None, edge_clip: float = 0.1) -> torch.Tensor:
    """Truncated edge strength in ``[0, 1]``: ``min(max(|grad gray|, |grad mask|) / edge_clip, 1)``.

    Gradients are kornia's normalised Sobel (a step of height ``c`` peaks near ``c / 2``). Either
    input may be ``None`` (grey only or silhouette only), not both.

    Shape: ``(B, H, W), (B, H, W) -> (B, H, W)``.
    """
    if gray is None and mask is None:
        raise ValueError("edge_map needs a grey image, a mask or both")
    if not edge_clip > 0:
        raise ValueError(f"edge_clip must be positive, got {edge_clip}")
    imgs = torch.stack([x for x in (gray, mask) if x is not None], 1)  # (B, 1 or 2, H, W)
    g = spatial_gradient(imgs, mode="sobel", order=1, normalized=True)  # (B, C, 2, H, W)
    mag = g.square().sum(2).sqrt().amax(1)
    return (mag / edge_clip).clamp(max=1.0)


def _odd(n: float) -> int:
    k = max(3, round(n))
    return k if k % 2 else k + 1


def dog(edges: torch.Tensor, canvas: int) -> torch.Tensor:
    """Difference of Gaussians of an edge map, kernel sizes ``odd(canvas / 20)`` and ``odd(canvas / 8)``.

    Sigma per kernel size ``k``: ``0.3 ((k - 1) / 2 - 1) + 0.8`` (OpenCV's default). Zero padding.

    Shape: ``(B, H, W) -> (B, H, W)``.
    """
    x = edges[:, None]
    out = []
    for k in (_odd(canvas / 20), _odd(canvas / 8)):
        s = 0.3 * ((k - 1) / 2 - 1) + 0.8
        out.append(gaussian_blur2d(x, (k, k), (s, s), border_type="constant"))
    return (out[0] - out[1])[:, 0]


def _scale(d: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Scale DoG maps ``(B, K, H, W)`` by ``0.5 / max|ref|`` per batch element, clip to ``[-0.5, 0.5]``."""
    peak = ref.abs().flatten(1).amax(1).clamp_min(1e-12)
    return (d * (0.5 / peak)[:, None, None, None]).clamp(-0.5, 0.5)


# -- hypotheses -------------------------------------------------------------------------------
def radial_gain(depth: torch.Tensor, origin, camera: Camera) -> torch.Tensor:
    """``mean_i |(u_i - cx, v_i - cy)| / Z_i`` over the object pixels of a render (pixels per metre).

    This is the mean image displacement per metre of motion along z (Eq. 9); 0 without object pixels.

    Shape: ``(B, h, w), (B, 2) -> (B,)``.
    """
    depth = _check_images(depth, "depth")
    B, h, w = depth.shape
    origin = _origin(origin, B, depth.dtype)
    u = torch.arange(w, dtype=depth.dtype)[None, None, :] + origin[:, 0, None, None] - camera.cx
    v = torch.arange(h, dtype=depth.dtype)[None, :, None] + origin[:, 1, None, None] - camera.cy
    mask = depth > 0
    r = torch.sqrt(u * u + v * v) / torch.where(mask, depth, torch.ones_like(depth))
    return (r * mask).flatten(1).sum(1) / mask.flatten(1).sum(1).clamp_min(1)


def hypothesis_steps(
    pose: torch.Tensor, camera: Camera, gain: torch.Tensor, dp_px: float = 1.0, dtheta_deg: float = 0.5
) -> torch.Tensor:
    """The 13 hypothesis steps ``[dt (m), phi (rad)]`` around each pose (module docstring, item 3).

    Args:
        pose: ``(B, 7)`` poses; ``z = tz`` sets the x / y step.
        camera: frame camera (``fx``, ``fy``).
        gain: ``(B,)`` :func:`radial_gain` of the object (``dz = dp / gain``; 0 gives ``dz = 0``).
        dp_px: image motion of a translation step, pixels.
        dtheta_deg: rotation step, degrees.

    Shape: ``(B, 7), (B,) -> (B, 13, 6)``; row 0 is zero, row ``1 + 2 a`` is ``+`` along ``AXES[a]``.
    """
    z = pose[:, 2]
    gain = gain.to(pose.dtype)
    dz = torch.where(gain > 0, dp_px / gain.clamp_min(1e-12), torch.zeros_like(gain))
    th = torch.full_like(z, math.radians(dtheta_deg))
    mag = torch.stack((z * dp_px / camera.fx, z * dp_px / camera.fy, dz, th, th, th), -1)  # (B, 6)
    plus = mag[:, :, None] * torch.eye(6, dtype=pose.dtype)  # (B, axis, 6)
    steps = torch.stack((plus, -plus), 2).reshape(-1, 12, 6)
    return torch.cat((torch.zeros_like(steps[:, :1]), steps), 1)


def apply_steps(pose: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """Poses moved by steps ``[dt, phi]``: ``t' = t + dt``, ``q' = exp(phi) (x) q``.

    Shape: ``(B, 7), (B, K, 6) -> (B, K, 7)``.
    """
    steps = steps.to(pose.dtype)
    t = pose[:, None, :3] + steps[..., :3]
    q = quat_mul(quat_exp(steps[..., 3:]), pose[:, None, 3:])
    return torch.cat((t, quat_canonical(q)), -1)


# -- warping and scoring ----------------------------------------------------------------------
def _fill_depth(depth: torch.Tensor, fallback: torch.Tensor, radius: int) -> torch.Tensor:
    """Background pixels (depth 0) get the mean object depth within ``radius`` or ``fallback`` (B,)."""
    mask = (depth > 0).to(depth.dtype)[:, None]
    k = 2 * radius + 1
    both = torch.cat((depth[:, None] * mask, mask), 1)
    both = F.avg_pool2d(F.avg_pool2d(both, (1, k), 1, (0, radius)), (k, 1), 1, (radius, 0))  # separable box
    num, den = both[:, :1], both[:, 1:]
    local = torch.where(den > 0, num / den.clamp_min(1e-12), fallback[:, None, None, None].to(depth.dtype))
    return torch.where(mask > 0, depth[:, None], local)[:, 0]


# Cubic B-spline interpolation for the warp (module docstring, item 4): exact at the samples and
# neither blurring nor sharpening a sub-pixel sample of the smooth template.
_POLE = math.sqrt(3.0) - 2.0
_PREFILTER_RADIUS = 8  # |pole| ** 9 < 1e-5: truncation error of the FIR inverse of [1, 4, 1] / 6


def _spline_prefilter(x: torch.Tensor) -> torch.Tensor:
    """B-spline coefficients of images (separable FIR inverse of ``[1, 4, 1] / 6``, zero outside).

    Shape: ``(B, C, H, W) -> (B, C, H, W)``.
    """
    k = torch.arange(-_PREFILTER_RADIUS, _PREFILTER_RADIUS + 1, dtype=torch.float64)
    kern = ((-6 * _POLE / (1 - _POLE**2)) * _POLE ** k.abs()).to(x.dtype)
    B, C, H, W = x.shape
    y = F.conv2d(x.reshape(B * C, 1, H, W), kern.view(1, 1, 1, -1), padding=(0, _PREFILTER_RADIUS))
    y = F.conv2d(y, kern.view(1, 1, -1, 1), padding=(_PREFILTER_RADIUS, 0))
    return y.reshape(B, C, H, W)


def _spline_sample(coef: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Evaluate the cubic B-spline with coefficients ``coef`` at pixel coordinates ``uv``.

    Per axis the 4 spline weights fold into 2 linear fetches with positive weights, so a point
    costs 4 bilinear fetches, all in one ``grid_sample`` call.

    Shape: ``(M, C, H, W), (M, 2, h, w) -> (M, C, h, w)`` with ``uv[:, 0] = u``, ``uv[:, 1] = v``.
    """
    M, C, H, W = coef.shape
    h, w = uv.shape[2:]
    i = torch.floor(uv)
    t = uv - i
    s = 1 - t
    t2 = t * t
    w0, w1, w3 = s * s * s / 6, 2 / 3 - t2 + t2 * t / 2, t2 * t / 6  # w2 = 1 - w0 - w1 - w3
    g0 = w0 + w1
    g = torch.stack((g0, 1 - g0), 1)  # (M, 2 fetches, 2 axes, h, w)
    pos = torch.stack((i - 1 + w1 / g0, i + 1 + w3 / (1 - g0)), 1)
    size = torch.tensor([W, H], dtype=uv.dtype).view(1, 1, 2, 1, 1)
    pos = (2 * pos + 1) / size - 1
    ex = (M, 2, 2, h, w)  # (y fetch, x fetch)
    grid = torch.stack((pos[:, None, :, 0].expand(ex), pos[:, :, None, 1].expand(ex)), -1).reshape(M, 4 * h, w, 2)
    out = F.grid_sample(coef, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    weights = (g[:, :, None, 1] * g[:, None, :, 0]).reshape(M, 1, 4, h, w)  # (y fetch, x fetch) order
    return (out.reshape(M, C, 4, h, w) * weights).sum(2)


def warp_canvas(
    images: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, base_pose: torch.Tensor, poses: torch.Tensor
) -> torch.Tensor:
    """Predict canvas images at other poses from one canvas rendered at ``base_pose`` (inverse warp).

    Canvas pixel ``q`` of the image at pose ``T`` samples the base image at
    ``project(T_0 T^-1 backproject(q, Z(q)))`` with ``Z`` the base depth (background filled from the
    object's neighbourhood): see the module docstring, item 4.

    Args:
        images: ``(B, C, N, N)`` canvas images at ``base_pose``.
        depth: ``(B, N, N)`` canvas depth at ``base_pose`` (metres, 0 = background).
        K: ``(B, 4)`` canvas intrinsics ``[fx, fy, cx, cy]`` (:func:`canvas_intrinsics`).
        base_pose: ``(B, 7)``.
        poses: ``(B, P, 7)`` target poses.

    Shape: returns ``(B, P, C, N, N)``.
    """
    B, C, N, _ = images.shape
    P = poses.shape[1]
    dt = images.dtype
    R0 = quat_to_matrix(base_pose[:, 3:])  # (B, 3, 3)
    R = quat_to_matrix(poses[..., 3:])  # (B, P, 3, 3)
    A = R0[:, None] @ R.transpose(-1, -2)  # X = A X' + b
    b = base_pose[:, None, :3] - (A @ poses[..., :3, None])[..., 0]
    # In homogeneous canvas pixels: p = Z(q) H q + e with H = Kc A Kc^-1 and e = Kc b.
    Kc = torch.zeros(B, 3, 3, dtype=A.dtype)
    Kc[:, 0, 0], Kc[:, 1, 1], Kc[:, 0, 2], Kc[:, 1, 2], Kc[:, 2, 2] = K[:, 0], K[:, 1], K[:, 2], K[:, 3], 1.0
    H = (Kc[:, None] @ A @ torch.linalg.inv(Kc)[:, None]).to(dt)  # (B, P, 3, 3)
    e = (Kc[:, None] @ b[..., None]).to(dt)  # (B, P, 3, 1)
    Z = _fill_depth(depth.to(dt), base_pose[:, 2], max(1, N // 16)).reshape(B, 1, 1, N * N)
    v, u = torch.meshgrid(torch.arange(N, dtype=dt), torch.arange(N, dtype=dt), indexing="ij")
    q = torch.stack((u.flatten(), v.flatten(), torch.ones(N * N, dtype=dt)))  # (3, N * N)
    p = Z * (H @ q) + e  # (B, P, 3, N * N)
    uv = (p[:, :, :2] / p[:, :, 2:].clamp_min(1e-9)).reshape(B * P, 2, N, N)
    coef = _spline_prefilter(images)[:, None].expand(B, P, C, N, N).reshape(B * P, C, N, N)
    return _spline_sample(coef, uv).reshape(B, P, C, N, N)


class CanvasRender(NamedTuple):
    """A render resampled into the canvas (:func:`prepare_canvas`).

    Attributes:
        box: ``(B, 3)`` ``[cu, cv, side]`` frame pixels of the canvas region.
        K: ``(B, 4)`` canvas intrinsics ``[fx, fy, cx, cy]``.
        depth: ``(B, N, N)`` metres, 0 = background (object depths only, no blending with 0).
        mask: ``(B, N, N)`` object coverage in ``[0, 1]`` (bilinear).
        gray: ``(B, N, N)`` shaded grey or ``None``.
    """

    box: torch.Tensor
    K: torch.Tensor
    depth: torch.Tensor
    mask: torch.Tensor
    gray: torch.Tensor | None


def prepare_canvas(
    depth: torch.Tensor,
    gray: torch.Tensor | None,
    origin,
    camera: Camera,
    canvas: int = 128,
    margin_px: float = 20.0,
    box: torch.Tensor | None = None,
) -> CanvasRender:
    """Resample a render (window at ``origin``) into the canvas; ``box`` defaults to :func:`canvas_box`.

    Shape: ``(B, h, w), (B, h, w) or None, (B, 2) -> CanvasRender`` with ``N = canvas``.
    """
    depth = _check_images(depth, "depth")
    if box is None:
        box = canvas_box(depth, origin, margin_px)
    mask = (depth > 0).to(depth.dtype)
    chans = torch.stack((depth * mask, mask) + (() if gray is None else (gray.to(depth.dtype),)), 1)
    c = to_canvas(chans, box, canvas, origin)
    c_mask = c[:, 1]
    c_depth = c[:, 0] / c_mask.clamp_min(1e-6) * (c_mask > 1e-6)
    return CanvasRender(box, canvas_intrinsics(box, camera, canvas), c_depth, c_mask, None if gray is None else c[:, 2])


def hypothesis_templates(
    cr: CanvasRender,
    base_pose: torch.Tensor,
    poses: torch.Tensor,
    *,
    edge_clip: float = 0.1,
    silhouette: bool = True,
    warp: str = "template",
) -> torch.Tensor:
    """Templates at ``poses`` predicted from the canvas render ``cr`` made at ``base_pose``.

    ``warp="template"``: Sobel + DoG of the base canvas, scaled to ``[-0.5, 0.5]``, then warped.
    ``warp="image"``: grey and mask warped, then Sobel + DoG per pose, all scaled by the base
    template's peak. See the module docstring (items 2 and 4).

    Shape: ``CanvasRender, (B, 7), (B, P, 7) -> (B, P, N, N)``.
    """
    sil = cr.mask if silhouette else None
    if cr.gray is None and sil is None:
        raise ValueError("without a grey render the template needs silhouette=True")
    N = cr.mask.shape[-1]
    base = dog(edge_map(cr.gray, sil, edge_clip), N)[:, None]
    if warp == "template":
        return warp_canvas(_scale(base, base), cr.depth, cr.K, base_pose, poses)[:, :, 0]
    if warp != "image":
        raise ValueError(f"warp must be 'template' or 'image', got {warp!r}")
    w = warp_canvas(torch.stack([x for x in (cr.gray, sil) if x is not None], 1), cr.depth, cr.K, base_pose, poses)
    B, P = w.shape[:2]
    g = None if cr.gray is None else w[:, :, 0].flatten(0, 1)
    m = None if sil is None else w[:, :, -1].flatten(0, 1)
    return _scale(dog(edge_map(g, m, edge_clip), N).reshape(B, P, N, N), base)


def score(templates: torch.Tensor, observation: torch.Tensor) -> torch.Tensor:
    """``sum(template * observation)`` over the canvas. Shape: ``(B, K, N, N), (B, N, N) -> (B, K)``."""
    return torch.einsum("bkhw,bhw->bk", templates, observation.to(templates.dtype))


def select(
    pose: torch.Tensor, steps: torch.Tensor, scores: torch.Tensor, rule: str = "argmax"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply the update rule to hypothesis scores.

    ``"argmax"``: the best hypothesis (ties go to the lowest index, so to the null).
    ``"group"``: per group ``GROUPS`` the best ``+/-`` step of its axes, applied if it beats the null
    score strictly; applied steps compose in group order (translations add, rotations
    ``exp(phi_last) ... exp(phi_first) (x) q``).

    Shape: ``(B, 7), (B, 13, 6), (B, 13) -> (B, 7) pose, (B, 13) bool applied``.
    """
    B = pose.shape[0]
    if rule == "argmax":
        idx = scores.argmax(1)
        applied = F.one_hot(idx, NUM_HYPOTHESES).bool() & (idx > 0)[:, None]
        return apply_steps(pose, steps.gather(1, idx[:, None, None].expand(B, 1, 6)))[:, 0], applied
    if rule != "group":
        raise ValueError(f"rule must be 'argmax' or 'group', got {rule!r}")
    applied = torch.zeros(B, NUM_HYPOTHESES, dtype=torch.bool, device=scores.device)
    t = pose[:, :3].clone()
    q = pose[:, 3:]
    for axes in GROUPS:
        cand = torch.tensor([1 + 2 * a + s for a in axes for s in (0, 1)], device=scores.device)
        best = scores[:, cand].argmax(1)
        idx = cand[best]
        ok = scores.gather(1, idx[:, None])[:, 0] > scores[:, 0]
        step = steps.gather(1, idx[:, None, None].expand(B, 1, 6))[:, 0] * ok[:, None].to(steps.dtype)
        t = t + step[:, :3].to(t.dtype)
        q = quat_mul(quat_exp(step[:, 3:].to(q.dtype)), q)
        applied[torch.arange(B), idx] |= ok
    return torch.cat((t, quat_canonical(q)), -1), applied


# -- the stage --------------------------------------------------------------------------------
def correct(
    pose: torch.Tensor,
    depth: torch.Tensor,
    gray: torch.Tensor | None,
    origin,
    observation: torch.Tensor,
    camera: Camera,
    *,
    observation_origin=(0, 0),
    canvas: int = 128,
    margin_px: float = 20.0,
    dp_px: float = 1.0,
    dtheta_deg: float = 0.5,
    rule: str = "argmax",
    iterations: int = 1,
    edge_clip: float = 0.1,
    silhouette: bool = True,
    warp: str = "template",
) -> Correction:
    """Correct propagated poses by matching warped templates of one render against the observation.

    Args:
        pose: ``(B, 7)`` propagated poses (the render's poses).
        depth: ``(B, h, w)`` render depth (metres, 0 = background) of the window at ``origin``.
        gray: ``(B, h, w)`` shaded grey render in ``[0, 1]`` (background 0), or ``None`` for
            silhouette edges only.
        origin: ``(B, 2)`` or ``(2,)`` frame pixel of the render window's top-left pixel.
        observation: ``(B, H, W)`` observation surface in ``[0, 1]`` (median-blurred EROS).
        camera: the frame camera.
        observation_origin: frame pixel of the observation's top-left pixel (default: full frame).
        canvas: canvas size in pixels (100..150 in the paper).
        margin_px: margin around the object's bounding box, frame pixels.
        dp_px, dtheta_deg: translation step (image pixels) and rotation step (degrees).
        rule: ``"argmax"`` (the paper) or ``"group"`` (EDOPT).
        iterations: maximum corrections per call; repeats while the score keeps improving.
        edge_clip: Sobel magnitude at which edges saturate (:func:`edge_map`).
        silhouette: add the mask's edges to the grey edges.
        warp: ``"template"`` (warp the finished template) or ``"image"`` (warp grey and mask, then
            filter each hypothesis).

    Returns:
        :class:`Correction`.

    Shape: ``(B, 7), (B, h, w), (B, h, w), (B, 2), (B, H, W) -> Correction``.
    """
    pose = _check_poses(pose, "pose")
    depth = _check_images(depth, "depth")
    B = pose.shape[0]
    if depth.shape[0] != B:
        raise ValueError(f"depth must have one image per pose ({B}), got {tuple(depth.shape)}")
    if gray is not None:
        gray = _check_images(gray, "gray")
        if gray.shape != depth.shape:
            raise ValueError(f"gray must match depth {tuple(depth.shape)}, got {tuple(gray.shape)}")
    elif not silhouette:
        raise ValueError("without a grey render the template needs silhouette=True")
    observation = _check_images(observation, "observation")
    if observation.shape[0] != B:
        raise ValueError(f"observation must have one image per pose ({B}), got {tuple(observation.shape)}")
    if rule not in ("argmax", "group"):
        raise ValueError(f"rule must be 'argmax' or 'group', got {rule!r}")
    if warp not in ("template", "image"):
        raise ValueError(f"warp must be 'template' or 'image', got {warp!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    if isinstance(canvas, bool) or not isinstance(canvas, int) or canvas < 16:
        raise ValueError(f"canvas must be an integer >= 16 pixels, got {canvas!r}")

    cr = prepare_canvas(depth, gray, origin, camera, canvas, margin_px)
    obs = to_canvas(observation.to(depth.dtype), cr.box, canvas, observation_origin)
    gain = radial_gain(depth, origin, camera)

    def templates(poses: torch.Tensor) -> torch.Tensor:
        return hypothesis_templates(cr, pose, poses, edge_clip=edge_clip, silhouette=silhouette, warp=warp)

    current = pose
    current_score = None
    active = torch.ones(B, dtype=torch.bool)
    moved = torch.zeros(B, dtype=torch.int64)
    first = None
    for _ in range(iterations):
        steps = hypothesis_steps(current, camera, gain, dp_px, dtheta_deg)
        hyp = apply_steps(current, steps)
        s = score(templates(hyp), obs)
        new_pose, applied = select(current, steps, s, rule)
        if rule == "argmax":
            new_score = s.gather(1, s.argmax(1, keepdim=True))[:, 0]
        else:
            new_score = score(templates(new_pose[:, None]), obs)[:, 0]
        if first is None:
            first = (s, s.argmax(1), applied)
            current_score = s[:, 0]
        step = active & applied.any(1)
        current = torch.where(step[:, None], new_pose, current)
        current_score = torch.where(step, new_score, current_score)
        moved += step.long()
        active = step & (new_score > s[:, 0])
        if not bool(active.any()):
            break
    return Correction(current, current_score, first[0], first[1], first[2], moved)


class TemplateCorrector(nn.Module):
    """Local template correction (configuration holder around :func:`correct`).

    Args:
        camera: the frame camera.
        canvas, margin_px, dp_px, dtheta_deg, rule, iterations, edge_clip, silhouette, warp: see
            :func:`correct`.

    ``forward(pose, depth, gray, origin, observation, observation_origin=(0, 0)) -> Correction``;
    ``correct_render(pose, render, origin, observation)`` takes a
    :class:`torchevtrack.render.Render` of the window at ``origin``.
    """

    def __init__(
        self,
        camera: Camera,
        canvas: int = 128,
        margin_px: float = 20.0,
        dp_px: float = 1.0,
        dtheta_deg: float = 0.5,
        rule: str = "argmax",
        iterations: int = 1,
        edge_clip: float = 0.1,
        silhouette: bool = True,
        warp: str = "template",
    ) -> None:
        super().__init__()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a torchevtrack Camera, got {type(camera).__name__}")
        if rule not in ("argmax", "group"):
            raise ValueError(f"rule must be 'argmax' or 'group', got {rule!r}")
        if warp not in ("template", "image"):
            raise ValueError(f"warp must be 'template' or 'image', got {warp!r}")
        if not (dp_px > 0 and dtheta_deg > 0 and margin_px >= 0 and edge_clip > 0):
            raise ValueError("dp_px, dtheta_deg and edge_clip must be positive and margin_px non-negative")
        self.camera = camera
        self.options = dict(
            canvas=canvas, margin_px=margin_px, dp_px=dp_px, dtheta_deg=dtheta_deg, rule=rule,
            iterations=iterations, edge_clip=edge_clip, silhouette=silhouette, warp=warp,
        )

    def forward(self, pose, depth, gray, origin, observation, observation_origin=(0, 0)) -> Correction:
        return correct(
            pose, depth, gray, origin, observation, self.camera, observation_origin=observation_origin, **self.options
        )

    def correct_render(self, pose, render, origin, observation, observation_origin=(0, 0)) -> Correction:
        """:meth:`forward` with a render result (``.depth``, ``.gray``) of the window at ``origin``."""
        return self(pose, render.depth, render.gray, origin, observation, observation_origin)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.options.items())


# -- input checks -----------------------------------------------------------------------------
def _check_poses(pose, name: str) -> torch.Tensor:
    if not isinstance(pose, torch.Tensor) or not pose.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor (B, 7), got {type(pose).__name__}")
    if pose.ndim != 2 or pose.shape[1] != 7:
        raise ValueError(f"{name} must have shape (B, 7) [tx, ty, tz, qw, qx, qy, qz], got {tuple(pose.shape)}")
    if (pose[:, 2] <= 0).any():
        raise ValueError(f"{name} places the object behind the camera (tz <= 0)")
    return pose


def _check_images(x, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor (B, H, W), got {type(x).__name__}")
    if x.ndim != 3 or x.shape[1] == 0 or x.shape[2] == 0:
        raise ValueError(f"{name} must have shape (B, H, W), got {tuple(x.shape)}")
    return x


def _origin(origin, B: int, dtype: torch.dtype) -> torch.Tensor:
    o = torch.as_tensor(origin, dtype=dtype)
    if o.shape == (2,):
        o = o.expand(B, 2)
    if o.shape != (B, 2):
        raise ValueError(f"origin must be (u0, v0) or a (B, 2) tensor, got shape {tuple(o.shape)}")
    return o
