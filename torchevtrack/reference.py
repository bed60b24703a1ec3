"""Torch reference implementations of the template correction: warp scoring (dense, per-pixel tensors).

The tracker's correction (:mod:`torchevtrack.stages.template`) scores hypotheses with a second-order model of the
warp, in compiled loops. This module is the dense torch form of the same steps (module docstring of
:mod:`torchevtrack.stages.template`, items 1-4): canvas box and crop (:func:`prepare_canvas`), template
(:func:`edge_map`, :func:`dog`), the warp of one render to 13 hypothesis templates (:func:`warp_canvas`,
:func:`hypothesis_templates`, cubic B-spline sampling) and the score (:func:`score`). Tests use it as the oracle of
the compiled kernels; ``tools/bench_template.py`` compares the two. :func:`correct_warp` is the full correction with
warped templates, a drop-in for :func:`correct`.

The decision rules of the correction (item 5 of :mod:`torchevtrack.stages.template`) are here too: the hypothesis
steps (:func:`hypothesis_steps`), the paper's argmax and EDOPT's group rule (:func:`select`), the torch Newton step
(:func:`newton_step`) and the search over them (:func:`search`, :func:`rule_search`), with the functional correction
:func:`correct`. The tracker reaches the argmax and group rules through the ablation switch ``template.rule``
(:func:`torchevtrack.stages.template.correct_canvas`); its default ``"newton"`` runs the compiled
:func:`~torchevtrack.stages.template.newton_search`, of which :func:`newton_step` is the oracle.

Conventions as in :mod:`torchevtrack.stages.template`: poses ``(B, 7)`` ``[t (m), q]``, renders ``(B, h, w)``
depth in metres (0 = background) of a window whose top-left frame pixel is ``origin``, canvases ``(B, N, N)``.

Example:
    >>> import torch
    >>> from torchevtrack.reference import dog, edge_map
    >>> mask = torch.zeros(1, 32, 32); mask[:, 8:24, 8:24] = 1
    >>> t = dog(edge_map(None, mask), 32)
    >>> tuple(t.shape), float(t.abs().max()) <= 0.5
    ((1, 32, 32), True)
"""

from __future__ import annotations

import functools
import inspect
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_canonical, quat_exp, quat_mul, quat_to_matrix
from torchevtrack.kernels import kernel
from torchevtrack.stages.template import (NEWTON_DAMPING, NEWTON_MAX_STEP, NUM_HYPOTHESES, PREFILTER_RADIUS, Correction,
                                          TemplateModel, apply_steps, area_weight, batch_origin, canvas_intrinsics,
                                          check_correct, check_images, correct_canvas, fill_kernel, gaussian_taps,
                                          odd_size, prefilter_taps, template_model, to_canvas, window_extent)

__all__ = ["canvas_box", "edge_map", "dog", "radial_gain", "warp_canvas", "CanvasRender", "prepare_canvas",
           "hypothesis_templates", "score", "GROUPS", "hypothesis_steps", "select", "newton_step", "search",
           "rule_search", "correct", "correct_model", "correct_warp"]


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
    depth = check_images(depth, "depth")
    return _box_of(_object_extent(depth, origin), depth, origin, margin_px)


def _box_of(extent: torch.Tensor, depth: torch.Tensor, origin, margin_px: float) -> torch.Tensor:
    """:func:`canvas_box` from the :func:`_object_extent` of the render ``depth``."""
    B, h, w = depth.shape
    origin = batch_origin(origin, B, depth.dtype)
    e = extent.to(depth.dtype)
    umin, umax, vmin, vmax = e[:, 0], e[:, 1], e[:, 2], e[:, 3]
    empty = e[:, 5] == 0
    cu = torch.where(empty, (w - 1) / 2.0, (umin + umax) / 2) + origin[:, 0]
    cv = torch.where(empty, (h - 1) / 2.0, (vmin + vmax) / 2) + origin[:, 1]
    side = torch.where(empty, float(max(h, w)), torch.maximum(umax - umin, vmax - vmin) + 1 + 2 * margin_px)
    return torch.stack((cu, cv, side), -1)


def _object_extent(depth: torch.Tensor, origin, camera: Camera | None = None) -> torch.Tensor:
    """One compiled pass over the ``depth > 0`` pixels of renders ``(B, h, w)`` (window at ``origin``).

    Returns ``(B, 6)`` float64: the window-pixel bounds ``umin, umax, vmin, vmax`` (0 without object pixels),
    the sum of ``|(u - cx, v - cy)| / Z`` over the object pixels (frame pixels ``u, v``; 0 without a
    ``camera``) and their count.
    """
    B = depth.shape[0]
    o = batch_origin(origin, B, torch.float64)
    c = (0.0, 0.0) if camera is None else (camera.cx, camera.cy)
    out = torch.empty(B, 6, dtype=torch.float64)
    _extent_kernel(depth.detach().numpy(), o.numpy(), c[0], c[1], camera is not None, out.numpy())
    return out


@kernel
def _extent_kernel(depth, origin, cx, cy, gain, out):
    for b in range(depth.shape[0]):
        out[b] = window_extent(depth[b], origin[b, 0], origin[b, 1], cx, cy, gain)


def edge_map(gray: torch.Tensor | None, mask: torch.Tensor | None, edge_clip: float = 0.1) -> torch.Tensor:
    """Truncated edge strength in ``[0, 1]``: ``min(max(|grad gray|, |grad mask|) / edge_clip, 1)``.

    Gradients are the normalised Sobel (``/ 8``, replicated border; as kornia's ``spatial_gradient``;
    a step of height ``c`` peaks near ``c / 2``). Either
    input may be ``None`` (grey only or silhouette only), not both.

    Shape: ``(B, H, W), (B, H, W) -> (B, H, W)``.
    """
    if gray is None and mask is None:
        raise ValueError("edge_map needs a grey image, a mask or both")
    if not edge_clip > 0:
        raise ValueError(f"edge_clip must be positive, got {edge_clip}")
    imgs = torch.stack([x for x in (gray, mask) if x is not None], 1)  # (B, 1 or 2, H, W)
    p = F.pad(imgs, (1, 1, 1, 1), mode="replicate")
    du = p[..., 2:] - p[..., :-2]  # Sobel as [1, 2, 1] smoothing of central differences
    dv = p[..., 2:, :] - p[..., :-2, :]
    gu = du[..., :-2, :] + 2 * du[..., 1:-1, :] + du[..., 2:, :]
    gv = dv[..., :-2] + 2 * dv[..., 1:-1] + dv[..., 2:]
    mag = (gu * gu + gv * gv).amax(1).sqrt()  # 8 x the normalised Sobel magnitude
    return (mag * (0.125 / edge_clip)).clamp(max=1.0)


@functools.lru_cache(maxsize=16)
def _blur_matrix(k: int, n: int, dtype: torch.dtype) -> torch.Tensor:
    """``(n, n)`` matrix of the 1-D blur with :func:`gaussian_taps` ``k`` and zero padding (``A @ x``).

    Cached (a constant of ``k, n, dtype``; never modified in place).
    """
    i = torch.arange(n)
    off = i[None, :] - i[:, None] + k // 2  # column j contributes to row i with tap j - i + k // 2
    g = gaussian_taps(k, dtype)
    return torch.where((off >= 0) & (off < k), g[off.clamp(0, k - 1)], torch.zeros((), dtype=dtype))


def dog(edges: torch.Tensor, canvas: int) -> torch.Tensor:
    """Difference of Gaussians of an edge map, kernel sizes ``odd(canvas / 20)`` and ``odd(canvas / 8)``.

    Sigma per kernel size ``k``: ``0.3 ((k - 1) / 2 - 1) + 0.8`` (OpenCV's default). Zero padding.
    Each separable blur is a product with banded matrices: ``G_v X G_u^T``.

    Shape: ``(B, H, W) -> (B, H, W)``.
    """
    _, H, W = edges.shape
    out = None
    for sign, k in ((1.0, odd_size(canvas / 20)), (-1.0, odd_size(canvas / 8))):
        blur = _blur_matrix(k, H, edges.dtype) @ edges @ _blur_matrix(k, W, edges.dtype).T
        out = blur if out is None else out + sign * blur
    return out


def _scale(d: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Scale DoG maps ``(B, K, H, W)`` by ``0.5 / max|ref|`` per batch element, clip to ``[-0.5, 0.5]``."""
    peak = ref.abs().flatten(1).amax(1).clamp_min(1e-12)
    return (d * (0.5 / peak)[:, None, None, None]).clamp(-0.5, 0.5)


def radial_gain(depth: torch.Tensor, origin, camera: Camera) -> torch.Tensor:
    """``mean_i |(u_i - cx, v_i - cy)| / Z_i`` over the object pixels of a render (pixels per metre).

    This is the mean image displacement per metre of motion along z (Eq. 9); 0 without object pixels.

    Shape: ``(B, h, w), (B, 2) -> (B,)``.
    """
    depth = check_images(depth, "depth")
    return _gain_of(_object_extent(depth, origin, camera), depth.dtype)


def _gain_of(extent: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """:func:`radial_gain` from an :func:`_object_extent` with a camera."""
    return (extent[:, 4] / extent[:, 5].clamp_min(1)).to(dtype)


def _fill_depth(depth: torch.Tensor, fallback: torch.Tensor, radius: int) -> torch.Tensor:
    """Background pixels (depth 0) get the mean object depth within ``radius`` or ``fallback`` (B,)."""
    out = depth.clone(memory_format=torch.contiguous_format)
    _fill_kernel(out.numpy(), fallback.double().expand(depth.shape[0]).contiguous().numpy(), radius)
    return out


@kernel
def _fill_kernel(depth, fallback, r):
    """:func:`_fill_depth` in place."""
    for b in range(depth.shape[0]):
        fill_kernel(depth[b], fallback[b], r)


def _spline_prefilter(x: torch.Tensor) -> torch.Tensor:
    """B-spline coefficients of images (separable FIR inverse of ``[1, 4, 1] / 6``, zero outside).

    Shape: ``(B, C, H, W) -> (B, C, H, W)``.
    """
    kern = prefilter_taps(x.dtype)
    B, C, H, W = x.shape
    y = F.conv2d(x.reshape(B * C, 1, H, W), kern.view(1, 1, 1, -1), padding=(0, PREFILTER_RADIUS))
    y = F.conv2d(y, kern.view(1, 1, -1, 1), padding=(PREFILTER_RADIUS, 0))
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
    object's neighbourhood): see :mod:`torchevtrack.stages.template`, item 4.

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
    uv = _warp_sources(depth, K, base_pose, poses, images.dtype)
    coef = _spline_prefilter(images)[:, None].expand(B, P, C, N, N).reshape(B * P, C, N, N)
    return _spline_sample(coef, uv).reshape(B, P, C, N, N)


def _warp_sources(depth: torch.Tensor, K: torch.Tensor, base_pose: torch.Tensor, poses: torch.Tensor,
                  dt: torch.dtype) -> torch.Tensor:
    """Where each canvas pixel of the images at ``poses`` ``(B, P, 7)`` samples the base canvas (:func:`warp_canvas`):
    ``(B * P, 2, N, N)`` canvas coordinates ``(u, v)`` in ``dt``."""
    B, N, _ = depth.shape
    P = poses.shape[1]
    H, e = _warp_homography(K, base_pose, poses)
    Z = _fill_depth(depth.to(dt), base_pose[:, 2], max(1, N // 16)).reshape(B, 1, 1, N * N)
    p = Z * (H.to(dt) @ _homogeneous_grid(N, dt)) + e.to(dt)[..., None]  # (B, P, 3, N * N)
    return (p[:, :, :2] / p[:, :, 2:].clamp_min(1e-9)).reshape(B * P, 2, N, N)


def _warp_homography(K: torch.Tensor, base_pose: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverse warp from the canvas at ``poses`` ``(B, P, 7)`` to the base canvas at ``base_pose`` ``(B, 7)``:
    pixel ``q`` with base depth ``Z(q)`` samples ``p = Z(q) H q + e`` (homogeneous canvas pixels).

    ``H = Kc A Kc^-1`` and ``e = Kc b``, with ``X = A X' + b`` the base-frame position of a point ``X'`` of the
    object at the target pose and ``Kc`` the canvas intrinsics ``K`` ``(B, 4)``.

    Shape: returns ``H`` ``(B, P, 3, 3)`` and ``e`` ``(B, P, 3)``, in ``base_pose``'s dtype.
    """
    B = K.shape[0]
    R0 = quat_to_matrix(base_pose[:, 3:])  # (B, 3, 3)
    R = quat_to_matrix(poses[..., 3:])  # (B, P, 3, 3)
    A = R0[:, None] @ R.transpose(-1, -2)
    b = base_pose[:, None, :3] - (A @ poses[..., :3, None])[..., 0]
    Kc = torch.zeros(B, 3, 3, dtype=A.dtype)
    Kc[:, 0, 0], Kc[:, 1, 1], Kc[:, 0, 2], Kc[:, 1, 2], Kc[:, 2, 2] = K[:, 0], K[:, 1], K[:, 2], K[:, 3], 1.0
    H = Kc[:, None] @ A @ torch.linalg.inv(Kc)[:, None]
    return H, (Kc[:, None] @ b[..., None])[..., 0]


@functools.lru_cache(maxsize=8)
def _homogeneous_grid(N: int, dtype: torch.dtype) -> torch.Tensor:
    """``(3, N * N)`` homogeneous pixel coordinates ``(u, v, 1)`` of an ``N x N`` canvas, row-major (cached
    constant, never modified in place)."""
    v, u = torch.meshgrid(torch.arange(N, dtype=dtype), torch.arange(N, dtype=dtype), indexing="ij")
    return torch.stack((u.flatten(), v.flatten(), torch.ones(N * N, dtype=dtype)))


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


def _crop_to_boxes(depth: torch.Tensor, gray: torch.Tensor | None, origin, box: torch.Tensor):
    """The part of a render window that the canvas boxes ``(B, 3)`` sample (union over the batch).

    Returns ``(depth, gray, origin)`` of the crop; resampling it gives the same canvas as the window.
    """
    B, h, w = depth.shape
    o = batch_origin(origin, B, box.dtype)
    half = box[:, 2] / 2
    lo = torch.stack((box[:, 0] - half - o[:, 0], box[:, 1] - half - o[:, 1]), -1).amin(0).floor() - 1
    hi = torch.stack((box[:, 0] + half - o[:, 0], box[:, 1] + half - o[:, 1]), -1).amax(0).ceil() + 2
    (u0, v0), (u1, v1) = lo.long().tolist(), hi.long().tolist()
    u0, v0 = min(max(u0, 0), w - 1), min(max(v0, 0), h - 1)
    u1, v1 = max(min(u1, w), u0 + 1), max(min(v1, h), v0 + 1)
    if (u0, v0, u1, v1) == (0, 0, w, h):
        return depth, gray, o
    crop = (slice(None), slice(v0, v1), slice(u0, u1))
    return depth[crop], None if gray is None else gray[crop], o + torch.tensor([u0, v0], dtype=o.dtype)


def _canvas_and_gain(depth, gray, origin, camera: Camera, canvas: int, margin_px: float):
    """:func:`prepare_canvas` and :func:`radial_gain` of a render, both from the crop the canvas samples."""
    depth = check_images(depth, "depth")
    extent = _object_extent(depth, origin, camera)  # the crop below holds every object pixel: same gain
    box = _box_of(extent, depth, origin, margin_px)
    depth, gray, origin = _crop_to_boxes(depth, gray, origin, box)
    return prepare_canvas(depth, gray, origin, camera, canvas, margin_px, box), _gain_of(extent, depth.dtype)


def prepare_canvas(
    depth: torch.Tensor,
    gray: torch.Tensor | None,
    origin,
    camera: Camera,
    canvas: int = 128,
    margin_px: float = 20.0,
    box: torch.Tensor | None = None,
) -> CanvasRender:
    """Resample a render (window at ``origin``) into the canvas; ``box`` defaults to :func:`canvas_box`
    (and then only the part of the window under the box is read).

    Shape: ``(B, h, w), (B, h, w) or None, (B, 2) -> CanvasRender`` with ``N = canvas``.
    """
    depth = check_images(depth, "depth")
    if box is None:
        box = canvas_box(depth, origin, margin_px)
        depth, gray, origin = _crop_to_boxes(depth, gray, origin, box)
    mask = depth > 0
    chans = (torch.where(mask, depth, 0.0), mask.to(depth.dtype)) + (() if gray is None else (gray.to(depth.dtype),))
    chans = torch.stack(chans, 1)
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
    template's peak. See :mod:`torchevtrack.stages.template`, items 2 and 4.

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


# -- the correction's decision rules: the paper's argmax, EDOPT's groups and the torch Newton step ------------------
# EDOPT's groups of axes whose image motions look alike, as axis indices into AXES.
GROUPS = ((0, 4), (1, 3), (5,), (2,))


def hypothesis_steps(
    pose: torch.Tensor, camera: Camera, gain: torch.Tensor, dp_px: float = 1.0, dtheta_deg: float = 0.5
) -> torch.Tensor:
    """The 13 hypothesis steps ``[dt (m), phi (rad)]`` around each pose (:mod:`torchevtrack.stages.template`, item 3).

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


def newton_step(score_steps, unit: torch.Tensor, max_step: float = NEWTON_MAX_STEP,
                damping: float = NEWTON_DAMPING) -> torch.Tensor:
    """Damped Newton step of a score over the six axes, in units of the hypothesis steps.

    The score is fitted by a quadratic ``s0 + g . u + u^T H u / 2`` in step units ``u`` (``u_a = 1`` is
    one hypothesis step along ``AXES[a]``) from 28 evaluations (the centre, ``+/- e_a`` and
    ``e_a + e_b``; exact for the Taylor score model), and the maximiser of the damped model
    ``u = -(H - lambda I)^-1 g`` is clipped to ``[-max_step, max_step]`` per axis. ``lambda`` exceeds the
    largest eigenvalue of ``H`` by ``damping`` times the mean curvature magnitude, so flat or convex
    directions take short steps. All axes move together: coupled axes (``tx`` and ``ry``) share the
    evidence through ``H`` instead of both taking it.

    Args:
        score_steps: steps ``(B, K, 6)`` ``[dt (m), phi (rad)]`` -> scores ``(B, K)``.
        unit: ``(B, 6)`` step magnitudes (m, rad), as the diagonal of :func:`hypothesis_steps`.

    Shape: ``(B, 6) -> (B, 6)`` step ``[dt, phi]`` in metres and radians.
    """
    B, n = unit.shape
    eye = torch.eye(n, dtype=torch.float64, device=unit.device)
    iu, ju = torch.triu_indices(n, n, 1)
    pts = torch.cat((torch.zeros_like(eye[:1]), eye, -eye, eye[iu] + eye[ju])).to(unit.dtype)  # (28, 6)
    s = score_steps(pts[None] * unit[:, None]).double()
    s0, sp, sm, sij = s[:, 0], s[:, 1:1 + n], s[:, 1 + n:1 + 2 * n], s[:, 1 + 2 * n:]
    g = 0.5 * (sp - sm)
    H = torch.diag_embed(sp + sm - 2 * s0[:, None])
    off = sij - sp[:, iu] - sp[:, ju] + s0[:, None]
    H[:, iu, ju] = off
    H[:, ju, iu] = off
    lam = torch.linalg.eigvalsh(H)[:, -1].clamp_min(0) + damping * H.diagonal(dim1=1, dim2=2).abs().mean(1) + 1e-12
    u = torch.linalg.solve(lam[:, None, None] * eye - H, g[..., None])[..., 0]
    return u.clamp(-max_step, max_step).to(unit.dtype) * unit


def search(
    pose: torch.Tensor,
    scorer,
    gain: torch.Tensor,
    camera: Camera,
    *,
    dp_px: float = 1.0,
    dtheta_deg: float = 0.5,
    rule: str = "argmax",
    iterations: int = 1,
    max_dz: float = math.inf,
    z_ref: torch.Tensor | None = None,
) -> Correction:
    """Hypothesis search (:mod:`torchevtrack.stages.template`, items 3 and 5) with any scorer of poses.

    Args:
        pose: ``(B, 7)`` start poses.
        scorer: callable ``centre (B, 7) -> (score_steps, score_poses)``, called once per iteration
            with the current poses: ``score_steps`` maps steps ``(B, K, 6)`` to the scores ``(B, K)``
            of ``apply_steps(centre, steps)``, ``score_poses`` poses ``(B, P, 7)`` to scores.
        gain: ``(B,)`` :func:`~torchevtrack.reference.radial_gain` (sets the z step).
        camera, dp_px, dtheta_deg, rule, iterations: see :func:`correct`.
        max_dz, z_ref: the corrected depths stay within ``max_dz`` metres of ``z_ref`` ``(B,)`` (``None``:
            ``pose``'s depths): the newton rule clips each step's depth to the band; the others clip the chosen pose's
            depth and score it there, moving only if it still beats the centre.

    Shape: ``(B, 7) -> Correction``.
    """
    B = pose.shape[0]
    current = pose
    zc = pose[:, 2] if z_ref is None else z_ref.to(pose.dtype)
    z_lo, z_hi = zc - max_dz, zc + max_dz
    current_score = None
    active = torch.ones(B, dtype=torch.bool)
    moved = torch.zeros(B, dtype=torch.int64)
    first = None
    for _ in range(iterations):
        score_steps, score_poses = scorer(current)
        steps = hypothesis_steps(current, camera, gain, dp_px, dtheta_deg)
        s = score_steps(steps)
        if rule == "newton":
            # The pose moves only if the step's score beats the null; "applied" then flags no hypothesis.
            delta = newton_step(score_steps, steps[:, 1::2].diagonal(dim1=1, dim2=2))
            delta[:, 2] = torch.minimum(torch.maximum(delta[:, 2], z_lo - current[:, 2]), z_hi - current[:, 2])
            new_score = score_steps(delta[:, None])[:, 0]
            moves = new_score > s[:, 0]
            new_pose = apply_steps(current, delta[:, None])[:, 0]
            applied = torch.zeros_like(s, dtype=torch.bool)
        else:
            new_pose, applied = select(current, steps, s, rule)
            moves = applied.any(1)
            if rule == "argmax":
                new_score = s.gather(1, s.argmax(1, keepdim=True))[:, 0]
            else:
                new_score = score_poses(new_pose[:, None])[:, 0]
            z = new_pose[:, 2].clamp(z_lo, z_hi)
            clipped = z != new_pose[:, 2]
            if bool(clipped.any()):
                new_pose = torch.cat((new_pose[:, :2], z[:, None], new_pose[:, 3:]), 1)
                new_score = torch.where(clipped, score_poses(new_pose[:, None])[:, 0], new_score)
                moves = moves & (~clipped | (new_score > s[:, 0]))
        if first is None:
            first = (s, s.argmax(1), applied)
            current_score = s[:, 0]
        step = active & moves
        current = torch.where(step[:, None], new_pose, current)
        current_score = torch.where(step, new_score, current_score)
        moved += step.long()
        active = step & (new_score > s[:, 0])
        if not bool(active.any()):
            break
    return Correction(current, current_score, first[0], first[1], first[2], moved)


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
) -> Correction:
    """Correct propagated poses by matching templates predicted from one render against the observation.

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
        rule: ``"argmax"`` (the paper), ``"group"`` (EDOPT) or ``"newton"`` (all axes, sub-step; item 5).
        iterations: maximum corrections per call; repeats while the score keeps improving.
        edge_clip: Sobel magnitude at which edges saturate (:func:`edge_map`).
        silhouette: add the mask's edges to the grey edges.

    Returns:
        :class:`~torchevtrack.stages.template.Correction`.

    Shape: ``(B, 7), (B, h, w), (B, h, w), (B, 2), (B, H, W) -> Correction``.
    """
    check_correct(pose, depth, gray, observation, canvas=canvas, rule=rule, iterations=iterations,
                  silhouette=silhouette)
    model = template_model(pose, depth, gray, origin, camera, canvas=canvas, margin_px=margin_px,
                           edge_clip=edge_clip, silhouette=silhouette)
    return correct_model(model, pose, observation, camera, observation_origin=observation_origin, dp_px=dp_px,
                         dtheta_deg=dtheta_deg, rule=rule, iterations=iterations)


def correct_model(
    model: TemplateModel,
    pose: torch.Tensor,
    observation: torch.Tensor,
    camera: Camera,
    *,
    observation_origin=(0, 0),
    dp_px: float = 1.0,
    dtheta_deg: float = 0.5,
    rule: str = "argmax",
    iterations: int = 1,
) -> Correction:
    """:func:`correct` with a render's :class:`~torchevtrack.stages.template.TemplateModel`, around any pose near the
    render's: :func:`~torchevtrack.stages.template.correct_canvas` of the observation resampled into the model's canvas
    (:meth:`~torchevtrack.stages.template.TemplateModel.observe`).

    Shape: ``TemplateModel, (B, 7), (B, H, W) -> Correction``.
    """
    return correct_canvas(model, pose, model.observe(observation, observation_origin), camera, dp_px=dp_px,
                          dtheta_deg=dtheta_deg, rule=rule, iterations=iterations)


def rule_search(model: TemplateModel, pose: torch.Tensor, obs: torch.Tensor, camera: Camera, *, dp_px: float,
                dtheta_deg: float, rule: str, iterations: int, max_dz: float = math.inf,
                z_ref: torch.Tensor | None = None) -> Correction:
    """:func:`search` with the model's second-order score (:meth:`~torchevtrack.stages.template.TemplateModel.at`
    and ``fit_canvas``, refitted at every iteration's pose), unchecked: the ``"argmax"`` and ``"group"`` rules of
    :func:`~torchevtrack.stages.template.correct_canvas` (which checks the inputs and runs this), or ``"newton"``
    with the torch step :func:`newton_step` (the oracle of :func:`~torchevtrack.stages.template.newton_search`).
    With the model's ``interior > 0`` every score pays the area term of
    :func:`~torchevtrack.stages.template.newton_kernel`: ``-a (z_r / z)^2`` as its second-order Taylor model in
    ``tz`` around each centre, ``a`` from :func:`~torchevtrack.stages.template.area_weight`.

    Shape: ``TemplateModel, (B, 7), (B, N * N) -> Correction``; scores in the render's dtype.
    """
    dtype = model.depth.dtype
    N = model.depth.shape[-1]
    area = torch.tensor([area_weight(obs[b].double().numpy(), model.valid[b].numpy(), N, float(model.interior[b]))
                         for b in range(obs.shape[0])], dtype=torch.float64)
    z_r = model.render_pose[:, 2]

    def scorer(centre: torch.Tensor):
        quad = model.at(centre).fit_canvas(obs)
        zc = centre[:, 2:3].double()
        ac = (area * (z_r / centre[:, 2]) ** 2)[:, None]

        def area_term(dz):  # -ac (zc / (zc + dz))^2 to second order
            return -ac * (1 - 2 * dz / zc + 3 * dz ** 2 / zc ** 2)

        return (lambda steps: (quad.at_steps(steps) + area_term(steps[..., 2].double())).to(dtype),
                lambda poses: (quad.evaluate(poses) + area_term(poses[..., 2].double() - zc)).to(dtype))

    return search(pose, scorer, model.gain, camera, dp_px=dp_px, dtheta_deg=dtheta_deg, rule=rule,
                  iterations=iterations, max_dz=max_dz, z_ref=z_ref)


def correct_warp(pose: torch.Tensor, depth: torch.Tensor, gray: torch.Tensor | None, origin, observation: torch.Tensor,
                 camera: Camera, *, warp: str = "template", **options) -> Correction:
    """:func:`correct` with warped templates instead of the second-order score model.

    Args:
        pose, depth, gray, origin, observation, camera: as for :func:`correct`.
        warp: ``"template"`` (warp the finished template) or ``"image"`` (warp grey and mask, then filter each
            hypothesis).
        options: the keyword options of :func:`correct` (same defaults).

    Returns:
        :class:`~torchevtrack.stages.template.Correction`, scores in the render's dtype.

    Shape: ``(B, 7), (B, h, w), (B, h, w) or None, (B, 2), (B, H, W) -> Correction``.
    """
    o = {**_CORRECT_DEFAULTS, **options}
    if set(o) != set(_CORRECT_DEFAULTS):
        raise TypeError(f"unknown options {sorted(set(o) - set(_CORRECT_DEFAULTS))}")
    check_correct(pose, depth, gray, observation, **o)
    if warp not in ("template", "image"):
        raise ValueError(f"warp must be 'template' or 'image', got {warp!r}")
    cr, gain = _canvas_and_gain(depth, gray, origin, camera, o["canvas"], o["margin_px"])
    obs = to_canvas(observation.to(depth.dtype), cr.box, o["canvas"], o["observation_origin"])

    def score_poses(poses: torch.Tensor) -> torch.Tensor:
        t = hypothesis_templates(cr, pose, poses, edge_clip=o["edge_clip"], silhouette=o["silhouette"], warp=warp)
        return score(t, obs)

    return search(pose, lambda centre: (lambda steps: score_poses(apply_steps(centre, steps)), score_poses), gain,
                  camera, dp_px=o["dp_px"], dtheta_deg=o["dtheta_deg"], rule=o["rule"], iterations=o["iterations"])


_CORRECT_DEFAULTS = {k: p.default for k, p in inspect.signature(correct).parameters.items()
                     if p.kind is inspect.Parameter.KEYWORD_ONLY}
