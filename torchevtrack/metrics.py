"""Pose-tracking metrics (BOP toolkit / YCB-Video / EDOPT conventions).

All errors compare a predicted pose with the ground-truth pose at the same instant, both in the
package convention (object in the camera frame, ``[tx, ty, tz, qw, qx, qy, qz]``, metres):

* translation error ``te = ||t - t_gt||`` (m) and its camera-frame components ``t - t_gt``;
* geodesic rotation error ``re = arccos((tr(R R_gt^T) - 1) / 2)`` (rad), computed stably as
  ``2 atan2(|vec(q_rel)|, |w(q_rel)|)`` with ``q_rel = q (x) q_gt^*``, and its components, the
  rotation vector of ``R R_gt^T`` (camera frame);
* ADD ``mean_x ||(R x + t) - (R_gt x + t_gt)||`` and ADD-S ``mean_x min_y ||(R x + t) - (R_gt y + t_gt)||``
  over model points ``x, y`` (m);
* model points for ADD / ADD-S: the mesh vertices, or :data:`MESH_POINTS` of them at evenly spaced
  indices (:func:`mesh_points`, :func:`load_mesh_points`): ``eval`` and ``benchmark`` score with the same points;
* AUC of ADD / ADD-S on 0..10 cm: the area under the accuracy-threshold curve normalised to 1,
  computed as the exact integral ``mean(clip(1 - e / 0.1, 0, 1))`` (the limit of the YCB-Video
  ``linspace(0, 0.1, N)`` sum; the discrete version differs by ``O(1 / N)``);
* sequence statistics: ``RMSE = sqrt(mean e^2)`` and ``sigma = std(e)`` with the **population**
  standard deviation (divide by ``N``), as in the paper's table;
* the EDOPT failure rule: a sequence fails when ``te > 7 cm`` or ``re > 40 deg`` for 50 consecutive
  samples; the failure instant is the first sample of the first such run.

Predictions are aligned to the ground truth by interpolating the ground truth (linear translation,
slerp rotation) at the prediction times; predictions outside the ground-truth time range are dropped
and counted, never extrapolated.

Example:
    >>> import torch
    >>> from torchevtrack.metrics import evaluate
    >>> t = torch.arange(0, 100_000, 1000)
    >>> gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(100, 7)
    >>> pred = gt.clone(); pred[:, 0] += 0.01
    >>> round(evaluate(t, pred, t, gt)["rmse_t_cm"], 6)
    1.0
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchevtrack.stages.propagate import twist_between
from torchevtrack.geometry import (
    interpolate_poses,
    quat_canonical,
    quat_conj,
    quat_log,
    quat_mul,
    quat_rotate,
    quat_to_matrix,
    transform_points,
)

__all__ = [
    "translation_error",
    "rotation_error",
    "pose_errors",
    "add_error",
    "adds_error",
    "auc",
    "rmse",
    "failure_index",
    "twists_from_poses",
    "velocity_errors",
    "align_to_gt",
    "mesh_points",
    "load_mesh_points",
    "per_pose_errors",
    "evaluate",
    "sym_failed",
    "sym_rmse_r_deg",
]

AUC_MAX_M = 0.10
MESH_POINTS = 2000
"""Model points of ADD / ADD-S: at most this many mesh vertices (:func:`mesh_points`)."""
FAIL_T_M = 0.07
FAIL_R_DEG = 40.0
FAIL_WINDOW = 50


def _check_poses(poses: torch.Tensor, name: str) -> torch.Tensor:
    poses = torch.as_tensor(poses)
    if not torch.is_floating_point(poses):
        raise TypeError(f"{name} must be a floating-point tensor, got {poses.dtype}")
    poses = poses.to(torch.float64)
    if poses.shape[-1:] != (7,):
        raise ValueError(f"{name} must have shape (..., 7) [tx, ty, tz, qw, qx, qy, qz], got {tuple(poses.shape)}")
    if not torch.isfinite(poses).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    norm = poses[..., 3:].norm(dim=-1)
    if ((norm - 1).abs() > 1e-3).any():
        raise ValueError(f"{name} quaternions are not unit norm (max |1 - |q|| = {float((norm - 1).abs().max()):.3g})")
    return torch.cat((poses[..., :3], quat_canonical(poses[..., 3:])), dim=-1)


def _check_times(t_us: torch.Tensor, name: str) -> torch.Tensor:
    t_us = torch.as_tensor(t_us)
    if t_us.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"{name} must be integer microseconds (int64), got {t_us.dtype}")
    if t_us.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {tuple(t_us.shape)}")
    t_us = t_us.to(torch.int64)
    if (t_us[1:] < t_us[:-1]).any():
        raise ValueError(f"{name} must be sorted (non-decreasing)")
    return t_us


def _check_pair(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    pred, gt = _check_poses(pred, "pred"), _check_poses(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    return pred, gt


def translation_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Translation error ``||t - t_gt||`` (m). Shape: ``(..., 7), (..., 7) -> (...)``."""
    pred, gt = _check_pair(pred, gt)
    return (pred[..., :3] - gt[..., :3]).norm(dim=-1)


def rotation_error(pred: torch.Tensor, gt: torch.Tensor, axis: torch.Tensor | None = None) -> torch.Tensor:
    """Geodesic rotation error ``arccos((tr(R R_gt^T) - 1) / 2)`` in radians, in ``[0, pi]``.

    Evaluated as ``2 atan2(|vec(q_rel)|, |w(q_rel)|)``, ``q_rel = q (x) q_gt^*``, which stays accurate
    near 0 and pi where the arccos form loses precision.

    With ``axis`` ``(3,)`` (object frame, e.g. :func:`torchevtrack.mesh.symmetry_axis`), the error
    modulo rotations about that axis: the smallest geodesic error over ``R Rot(axis, theta)``, which is
    the angle between ``R axis`` and ``R_gt axis``.

    Shape: ``(..., 7), (..., 7) -> (...)``.
    """
    pred, gt = _check_pair(pred, gt)
    if axis is not None:
        return _axis_angle(pred, gt, axis)
    return _angle(quat_mul(pred[..., 3:], quat_conj(gt[..., 3:])))


def _axis_angle(pred: torch.Tensor, gt: torch.Tensor, axis) -> torch.Tensor:
    a = torch.as_tensor(axis, dtype=torch.float64)
    if a.shape != (3,) or not bool(torch.isfinite(a).all()) or float(a.norm()) == 0.0:
        raise ValueError(f"axis must be a finite non-zero (3,) vector, got {a.tolist()}")
    a = (a / a.norm()).expand(*pred.shape[:-1], 3)
    u, v = quat_rotate(pred[..., 3:].double(), a), quat_rotate(gt[..., 3:].double(), a)
    return torch.atan2(torch.linalg.cross(u, v, dim=-1).norm(dim=-1), (u * v).sum(-1))


def _angle(q: torch.Tensor) -> torch.Tensor:
    return 2.0 * torch.atan2(q[..., 1:].norm(dim=-1), q[..., 0].abs())


def pose_errors(pred: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-pose errors of matched poses.

    Returns ``te`` (m), ``re`` (rad), ``te_xyz = t - t_gt`` (m, camera frame) and ``re_xyz``, the
    rotation vector of ``R R_gt^T`` (rad, camera frame; its norm is ``re``).

    Shape: ``(..., 7), (..., 7) -> te, re (...)``, ``te_xyz, re_xyz (..., 3)``.
    """
    pred, gt = _check_pair(pred, gt)
    dt = pred[..., :3] - gt[..., :3]
    q_rel = quat_mul(pred[..., 3:], quat_conj(gt[..., 3:]))
    return {"te": dt.norm(dim=-1), "re": _angle(q_rel), "te_xyz": dt, "re_xyz": quat_log(q_rel)}


def _check_points(points: torch.Tensor) -> torch.Tensor:
    points = torch.as_tensor(points, dtype=torch.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"mesh_points must have shape (M, 3) with M >= 1, got {tuple(points.shape)}")
    if not torch.isfinite(points).all():
        raise ValueError("mesh_points contains NaN or infinite values")
    return points


def add_error(pred: torch.Tensor, gt: torch.Tensor, points: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """ADD: mean distance between model points moved by the predicted and the true pose (m).

    Processed in chunks of ``chunk`` poses to bound memory. Shape: ``(N, 7), (N, 7), (M, 3) -> (N,)``.
    """
    pred, gt = _check_pair(pred, gt)
    points = _check_points(points)
    if pred.ndim != 2:
        raise ValueError(f"pred and gt must have shape (N, 7), got {tuple(pred.shape)}")
    out = []
    for p, g in zip(pred.split(chunk), gt.split(chunk)):
        dR = quat_to_matrix(p[:, 3:]) - quat_to_matrix(g[:, 3:])  # (R - R_gt) x + (t - t_gt)
        out.append((points @ dR.transpose(-1, -2) + (p[:, None, :3] - g[:, None, :3])).norm(dim=-1).mean(dim=-1))
    return torch.cat(out) if out else pred.new_zeros(0)


def adds_error(pred: torch.Tensor, gt: torch.Tensor, points: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """ADD-S: mean over predicted model points of the distance to the nearest true model point (m).

    ``min_y ||R x + t - (R_gt y + t_gt)|| = min_y ||R_gt^T (R x + t - t_gt) - y||``, so the predicted
    points are mapped into the true object frame and one KD-tree of the model points answers every
    pose. Shape: ``(N, 7), (N, 7), (M, 3) -> (N,)``.
    """
    pred, gt = _check_pair(pred, gt)
    points = _check_points(points)
    if pred.ndim != 2:
        raise ValueError(f"pred and gt must have shape (N, 7), got {tuple(pred.shape)}")
    tree = cKDTree(points.numpy())
    out = []
    for p, g in zip(pred.split(chunk), gt.split(chunk)):
        cam = transform_points(p, points) - g[:, None, :3]  # (n, M, 3)
        local = cam @ quat_to_matrix(g[:, 3:])  # row-vector form of R_gt^T (.)
        dist, _ = tree.query(local.reshape(-1, 3).numpy(), k=1, workers=-1)
        out.append(torch.from_numpy(dist).reshape(local.shape[:2]).mean(dim=-1))
    return torch.cat(out) if out else pred.new_zeros(0)


def mesh_points(vertices, max_points: int = MESH_POINTS) -> torch.Tensor:
    """Model points for ADD / ADD-S: the vertices, or ``max_points`` of them at evenly spaced indices.

    Shape: ``(V, 3) -> (min(V, max_points), 3)`` float64, the vertices' units (metres). Deterministic.

    Example:
        >>> mesh_points(torch.arange(30.0).reshape(10, 3), max_points=3)[:, 0].tolist()
        [0.0, 12.0, 27.0]
    """
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {tuple(v.shape)}")
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    if v.shape[0] <= max_points:
        return v
    return v[torch.linspace(0, v.shape[0] - 1, max_points, dtype=torch.float64).round().long()]


def load_mesh_points(path: str | Path, max_points: int = MESH_POINTS) -> torch.Tensor:
    """:func:`mesh_points` of a mesh file's vertices, in file order (read as the sequence reader reads
    ``mesh.ply``: no vertex merging). Shape: ``-> (M, 3)`` float64, ``M <= max_points``."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot load mesh ({e})") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if v.ndim != 2 or v.shape[0] == 0:
        raise ValueError(f"{path}: mesh has no vertices")
    return mesh_points(v, max_points)


def auc(errors: torch.Tensor, max_threshold: float = AUC_MAX_M) -> float:
    """Area under the accuracy-threshold curve on ``[0, max_threshold]``, normalised to 1.

    Accuracy at threshold ``tau`` is the fraction of errors below ``tau``; its exact integral is
    ``mean(clip(1 - e / max_threshold, 0, 1))``. Shape: ``(N,) -> float``.
    """
    errors = torch.as_tensor(errors, dtype=torch.float64)
    if errors.ndim != 1 or errors.numel() == 0:
        raise ValueError(f"errors must have shape (N,) with N >= 1, got {tuple(errors.shape)}")
    if not max_threshold > 0:
        raise ValueError(f"max_threshold must be > 0, got {max_threshold}")
    return float((1.0 - errors / max_threshold).clamp(0.0, 1.0).mean())


def rmse(errors: torch.Tensor) -> float:
    """Root mean square ``sqrt(mean e^2)``. Shape: ``(N,) -> float``."""
    errors = torch.as_tensor(errors, dtype=torch.float64)
    return float(errors.square().mean().sqrt())


def failure_index(
    te: torch.Tensor,
    re: torch.Tensor,
    max_t: float = FAIL_T_M,
    max_r_deg: float = FAIL_R_DEG,
    window: int = FAIL_WINDOW,
) -> int | None:
    """EDOPT failure rule: index of the first sample of the first run of ``window`` consecutive samples
    with ``te > max_t`` (m) or ``re > max_r_deg`` (degrees), or ``None`` if there is no such run.

    Shape: ``(N,), (N,) -> int | None`` (samples in time order).
    """
    te, re = torch.as_tensor(te), torch.as_tensor(re)
    if te.shape != re.shape or te.ndim != 1:
        raise ValueError(f"te and re must have the same shape (N,), got {tuple(te.shape)} and {tuple(re.shape)}")
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    bad = ((te > max_t) | (re > math.radians(max_r_deg))).to(torch.int64)
    if bad.numel() < window:
        return None
    c = torch.cat((bad.new_zeros(1), bad.cumsum(0)))
    runs = (c[window:] - c[:-window]) == window  # runs[i]: samples i .. i+window-1 all bad
    hits = runs.nonzero()
    return int(hits[0, 0]) if hits.numel() else None


def twists_from_poses(t_us: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Camera-frame twists ``[v, w]`` by finite differences of a sampled trajectory.

    The package's twist convention (every object point moves as ``dP/dt = v + w x P``), from central
    differences inside and one-sided differences at both ends: the exact constant twist between the
    neighbouring samples (:func:`torchevtrack.stages.propagate.twist_between`). Units m/s and rad/s.
    Shape: ``(N,), (N, 7) -> (N, 6)`` with ``N >= 2`` and strictly increasing times.
    """
    t_us = _check_times(t_us, "t_us")
    poses = _check_poses(poses, "poses")
    if poses.shape != (t_us.shape[0], 7) or t_us.numel() < 2:
        raise ValueError(f"expected t_us (N,) and poses (N, 7) with N >= 2, got {tuple(t_us.shape)}, {tuple(poses.shape)}")
    if (t_us[1:] == t_us[:-1]).any():
        raise ValueError("t_us must be strictly increasing to differentiate poses")
    n = t_us.numel()
    hi = torch.arange(n).add(1).clamp(max=n - 1)
    lo = torch.arange(n).sub(1).clamp(min=0)
    dt = (t_us[hi] - t_us[lo]).to(torch.float64) * 1e-6
    return twist_between(poses[lo], poses[hi], dt)


def velocity_errors(pred_twist: torch.Tensor, gt_twist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Linear ``||v - v_gt||`` (m/s) and angular ``||w - w_gt||`` (rad/s) velocity errors.

    Shape: ``(..., 6), (..., 6) -> (...), (...)``.
    """
    pred_twist, gt_twist = torch.as_tensor(pred_twist), torch.as_tensor(gt_twist)
    if pred_twist.shape[-1:] != (6,) or pred_twist.shape != gt_twist.shape:
        raise ValueError(
            f"twists must both have shape (..., 6) [v, w], got {tuple(pred_twist.shape)} and {tuple(gt_twist.shape)}"
        )
    d = pred_twist.to(torch.float64) - gt_twist.to(torch.float64)
    return d[..., :3].norm(dim=-1), d[..., 3:].norm(dim=-1)


def align_to_gt(
    pred_t_us: torch.Tensor, pred_poses: torch.Tensor, gt_t_us: torch.Tensor, gt_poses: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ground truth interpolated at the prediction times (linear translation, slerp rotation).

    Predictions outside ``[gt_t_us[0], gt_t_us[-1]]`` are dropped (no extrapolation).
    Returns ``keep (N,) bool``, ``t_us (K,)``, ``pred (K, 7)``, ``gt (K, 7)``.

    Shape: ``(N,), (N, 7), (G,), (G, 7) -> (N,), (K,), (K, 7), (K, 7)``.
    """
    pred_t_us, gt_t_us = _check_times(pred_t_us, "pred_t_us"), _check_times(gt_t_us, "gt_t_us")
    pred_poses, gt_poses = _check_poses(pred_poses, "pred_poses"), _check_poses(gt_poses, "gt_poses")
    if pred_poses.shape != (pred_t_us.shape[0], 7):
        raise ValueError(f"pred_poses must have shape ({pred_t_us.shape[0]}, 7), got {tuple(pred_poses.shape)}")
    if gt_poses.shape != (gt_t_us.shape[0], 7) or gt_t_us.numel() == 0:
        raise ValueError(f"gt_poses must have shape ({gt_t_us.shape[0]}, 7) with at least one pose, got {tuple(gt_poses.shape)}")
    keep = (pred_t_us >= gt_t_us[0]) & (pred_t_us <= gt_t_us[-1])
    t = pred_t_us[keep]
    return keep, t, pred_poses[keep], interpolate_poses(gt_t_us, gt_poses, t)


def per_pose_errors(
    pred_t_us: torch.Tensor,
    pred_poses: torch.Tensor,
    gt_t_us: torch.Tensor,
    gt_poses: torch.Tensor,
    *,
    mesh_points: torch.Tensor | None = None,
    symmetry_axis: torch.Tensor | None = None,
    pred_twists: torch.Tensor | None = None,
    gt_twists: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Per-pose errors after time alignment (see :func:`align_to_gt`).

    Returns ``t_us (K,)``, ``keep (N,)`` (which predictions were evaluated), ``te, re, te_xyz,
    re_xyz`` (see :func:`pose_errors`), with ``mesh_points (M, 3)`` also ``add, adds (K,)`` (m), with
    ``symmetry_axis (3,)`` also ``re_sym (K,)``, the rotation error modulo that axis (:func:`rotation_error`), and
    with ``pred_twists (N, 6)`` also ``ev`` (m/s) and ``ew`` (rad/s) against ``gt_twists (G, 6)``
    given at the ground-truth times, or by default :func:`twists_from_poses` of the ground truth;
    ground-truth twists are linearly interpolated at the prediction times.
    """
    keep, t, pred, gt = align_to_gt(pred_t_us, pred_poses, gt_t_us, gt_poses)
    out = {"t_us": t, "keep": keep, **pose_errors(pred, gt)}
    if symmetry_axis is not None:
        out["re_sym"] = _axis_angle(pred, gt, symmetry_axis)
    if mesh_points is not None:
        out["add"] = add_error(pred, gt, mesh_points)
        out["adds"] = adds_error(pred, gt, mesh_points)
    if pred_twists is not None:
        pred_twists = torch.as_tensor(pred_twists, dtype=torch.float64)
        if pred_twists.shape != (keep.shape[0], 6):
            raise ValueError(f"pred_twists must have shape ({keep.shape[0]}, 6), got {tuple(pred_twists.shape)}")
        gt_t = torch.as_tensor(gt_t_us, dtype=torch.int64)
        if gt_twists is None:
            gt_twists = twists_from_poses(gt_t, gt_poses)
        gt_twists = torch.as_tensor(gt_twists, dtype=torch.float64)
        if gt_twists.shape != (gt_t.shape[0], 6):
            raise ValueError(f"gt_twists must have shape ({gt_t.shape[0]}, 6), got {tuple(gt_twists.shape)}")
        out["ev"], out["ew"] = velocity_errors(pred_twists[keep], _interp_linear(gt_t, gt_twists, t))
    return out


def _interp_linear(times: torch.Tensor, values: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    if times.numel() == 1:
        return values.expand(query.shape[0], values.shape[1]).clone()
    i1 = torch.searchsorted(times, query).clamp(1, times.numel() - 1)
    i0 = i1 - 1
    span = (times[i1] - times[i0]).to(torch.float64).clamp_min(1e-12)
    tau = ((query - times[i0]).to(torch.float64) / span).clamp(0, 1)[:, None]
    return values[i0] + (values[i1] - values[i0]) * tau


def _stats(e: torch.Tensor, scale: float, unit: str, name: str) -> dict[str, float]:
    e = e * scale
    return {
        f"rmse_{name}_{unit}": float(e.square().mean().sqrt()),
        f"std_{name}_{unit}": float(e.std(correction=0)),
        f"mean_{name}_{unit}": float(e.mean()),
        f"median_{name}_{unit}": float(e.median()),
        f"max_{name}_{unit}": float(e.max()),
    }


def evaluate(
    pred_t_us: torch.Tensor,
    pred_poses: torch.Tensor,
    gt_t_us: torch.Tensor,
    gt_poses: torch.Tensor,
    *,
    mesh_points: torch.Tensor | None = None,
    symmetric: bool = False,
    symmetry_axis: torch.Tensor | None = None,
    pred_twists: torch.Tensor | None = None,
    gt_twists: torch.Tensor | None = None,
) -> dict | list[dict]:
    """Sequence metrics of a predicted trajectory against the ground truth.

    Args:
        pred_t_us, pred_poses: predictions, int64 microseconds ``(N,)`` and poses ``(N, 7)``.
        gt_t_us, gt_poses: ground truth ``(G,)``, ``(G, 7)``, interpolated at the prediction times.
        mesh_points: model points ``(M, 3)`` (m) for ADD / ADD-S; without them those keys are ``None``.
        symmetric: the object is symmetric: ``add_s_auc`` (the ADD(-S) metric) then uses ADD-S.
        symmetry_axis: ``(3,)`` axis of a continuous rotational symmetry (object frame,
            :func:`torchevtrack.mesh.symmetry_axis`): adds the statistics of the rotation error modulo
            that axis (``rmse_r_sym_deg``, ...) and the EDOPT rule applied with it (``failed_sym``,
            ``first_failure_sym_s``).
        pred_twists, gt_twists: optional ``(N, 6)`` / ``(G, 6)`` twists for velocity errors
            (see :func:`per_pose_errors`).

    Returns a JSON-serialisable dict: ``n_poses`` (evaluated), ``n_dropped`` (outside the GT time
    range); ``rmse_/std_/mean_/median_/max_`` of ``t_cm`` and ``r_deg`` (std is the population
    standard deviation); ``rmse_t_xyz_cm`` and ``rmse_r_xyz_deg`` per axis (camera frame);
    ``add_auc, adds_auc, add_s_auc`` (0..1 on 0..10 cm), ``mean_add_cm, mean_adds_cm``;
    ``failed``, ``first_failure_index`` (into the evaluated poses) and ``first_failure_s``
    (prediction timestamp in seconds) by the EDOPT rule, ``None`` when not failed; with twists also
    ``rmse_v_cm_s`` and ``rmse_w_deg_s``.

    Batched: with ``pred_t_us (B, N)`` and ``pred_poses (B, N, 7)`` (e.g. the output of
    :meth:`~torchevtrack.tracker.EventPoseTracker.track`), a list of ``B`` such dicts, element ``i`` scored
    against its own ground truth ``gt_t_us[i] (G,)``, ``gt_poses[i] (G, 7)`` when those have a leading ``B``,
    else the shared ``(G,)``, ``(G, 7)``; likewise ``mesh_points`` ``(B, M, 3)`` or ``(M, 3)``,
    ``symmetry_axis`` ``(B, 3)`` or ``(3,)``, ``pred_twists`` ``(B, N, 6)`` and ``gt_twists`` ``(B, G, 6)`` or
    ``(G, 6)``. Each dict equals the unbatched call on that element.

    Example (batched):
        >>> t = torch.arange(0, 100_000, 1000)
        >>> gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(100, 7)
        >>> pred = torch.stack([gt, gt + torch.tensor([0.02, 0, 0, 0, 0, 0, 0])])
        >>> [round(r["rmse_t_cm"], 6) for r in evaluate(t.expand(2, 100), pred, t, gt)]
        [0.0, 2.0]
    """
    if torch.as_tensor(pred_poses).ndim == 3:
        return _evaluate_batch(pred_t_us, pred_poses, gt_t_us, gt_poses, mesh_points=mesh_points,
                               symmetric=symmetric, symmetry_axis=symmetry_axis, pred_twists=pred_twists,
                               gt_twists=gt_twists)
    e = per_pose_errors(
        pred_t_us, pred_poses, gt_t_us, gt_poses, mesh_points=mesh_points, symmetry_axis=symmetry_axis,
        pred_twists=pred_twists, gt_twists=gt_twists
    )
    n = int(e["t_us"].numel())
    n_dropped = int(e["keep"].numel()) - n
    if n == 0:
        raise ValueError(f"no prediction lies inside the ground-truth time range ({n_dropped} dropped)")
    deg = 180.0 / math.pi
    out: dict = {"n_poses": n, "n_dropped": n_dropped}
    out.update(_stats(e["te"], 100.0, "cm", "t"))
    out.update(_stats(e["re"], deg, "deg", "r"))
    out["rmse_t_xyz_cm"] = (e["te_xyz"] * 100.0).square().mean(0).sqrt().tolist()
    out["rmse_r_xyz_deg"] = (e["re_xyz"] * deg).square().mean(0).sqrt().tolist()
    if "add" in e:
        out["add_auc"] = auc(e["add"])
        out["adds_auc"] = auc(e["adds"])
        out["add_s_auc"] = out["adds_auc"] if symmetric else out["add_auc"]
        out["mean_add_cm"] = float(e["add"].mean()) * 100.0
        out["mean_adds_cm"] = float(e["adds"].mean()) * 100.0
    else:
        out.update(add_auc=None, adds_auc=None, add_s_auc=None, mean_add_cm=None, mean_adds_cm=None)
    k = failure_index(e["te"], e["re"])
    out["failed"] = k is not None
    out["first_failure_index"] = k
    out["first_failure_s"] = None if k is None else int(e["t_us"][k]) / 1e6
    if "re_sym" in e:
        out.update(_stats(e["re_sym"], deg, "deg", "r_sym"))
        k = failure_index(e["te"], e["re_sym"])
        out["failed_sym"] = k is not None
        out["first_failure_sym_s"] = None if k is None else int(e["t_us"][k]) / 1e6
    if "ev" in e:
        out["rmse_v_cm_s"] = rmse(e["ev"]) * 100.0
        out["rmse_w_deg_s"] = rmse(e["ew"]) * deg
    return out


def _evaluate_batch(pred_t_us, pred_poses, gt_t_us, gt_poses, *, mesh_points, symmetric, symmetry_axis,
                    pred_twists, gt_twists) -> list[dict]:
    """:func:`evaluate` of each batch element (see its batched form)."""
    pred_t_us, pred_poses = torch.as_tensor(pred_t_us), torch.as_tensor(pred_poses)
    B = pred_poses.shape[0]
    if pred_t_us.shape != pred_poses.shape[:2]:
        raise ValueError(f"batched pred_t_us must have shape {tuple(pred_poses.shape[:2])} like pred_poses (B, N, 7), "
                         f"got {tuple(pred_t_us.shape)}")

    def per(value, ndim: int, name: str):
        """Element i of a batched argument (leading B) or the shared one."""
        if value is None:
            return [None] * B
        value = torch.as_tensor(value)
        if value.ndim == ndim:
            return [value] * B
        if value.ndim != ndim + 1 or value.shape[0] != B:
            raise ValueError(f"{name} must be shared ({ndim} dims) or batched with a leading B={B}, "
                             f"got {tuple(value.shape)}")
        return list(value)

    if pred_twists is not None and torch.as_tensor(pred_twists).ndim != 3:
        raise ValueError(f"batched pred_twists must have shape ({B}, N, 6)")
    args = zip(per(gt_t_us, 1, "gt_t_us"), per(gt_poses, 2, "gt_poses"), per(mesh_points, 2, "mesh_points"),
               per(symmetry_axis, 1, "symmetry_axis"), per(pred_twists, 2, "pred_twists"),
               per(gt_twists, 2, "gt_twists"))
    return [evaluate(pred_t_us[i], pred_poses[i], gt_t, gt, mesh_points=pts, symmetric=symmetric, symmetry_axis=axis,
                     pred_twists=pt, gt_twists=gtw)
            for i, (gt_t, gt, pts, axis, pt, gtw) in enumerate(args)]


def sym_failed(metrics: dict) -> bool:
    """The EDOPT verdict of one run's :func:`evaluate` dict with the rotation about the symmetry axis left out where
    the run has one (``failed_sym``), else with the whole rotation (``failed``).

    Example:
        >>> sym_failed({"failed": True, "failed_sym": False}), sym_failed({"failed": True})
        (False, True)
    """
    return bool(metrics.get("failed_sym", metrics["failed"]))


def sym_rmse_r_deg(metrics: dict) -> float:
    """The rotation RMSE (deg) of one run's :func:`evaluate` dict with the symmetry axis left out where the run has
    one (``rmse_r_sym_deg``), else the whole rotation's (``rmse_r_deg``)."""
    return float(metrics.get("rmse_r_sym_deg", metrics["rmse_r_deg"]))
