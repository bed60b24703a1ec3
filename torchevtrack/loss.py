"""Tracking-loss detection from the tracker's per-update :class:`~torchevtrack.tracker.Quality`.

Per update and batch element (:func:`loss_kernel`, compiled):

* score support ``c_score = clip(score / reference, 0, 1)``. The template score's scale depends on the
  object and the scene, so it is compared with a running ``reference``: an exponential moving average
  (rate ``ema``) of the scores of confident updates, started at the first positive score (or at a given
  ``initial_reference``). Low scores never enter the reference, so a collapse stays visible. A NaN score
  (template correction off) gives ``c_score = 1``: no evidence either way.
* flow support ``c_flow = clip(flow_vectors / min_flow_vectors, 0, 1)`` (1 when ``min_flow_vectors = 0``,
  e.g. for ``velocity.source != "flow"``). Flow vectors are only counted near the rendered object, so an
  object that left its estimate, a window of noise or an empty window all give no flow.
* ``confidence = min(c_score, c_flow)`` in ``[0, 1]`` (0 for an update the tracker rejected).
* the update is **low** when it was rejected, ``c_score < score_threshold`` or ``flow_vectors <
  min_flow_vectors``. After ``patience`` consecutive low updates the element is ``lost``; it is found
  again after ``recovery`` consecutive confident updates (or a reset). An update whose ``Quality.burst`` is set
  (the burst guard dropped its events) is neutral: the element's state stays as it was.

Both signals need a few updates to build up after a (re)start (the EROS and the flow's time surface
start empty): ``patience`` must cover that warm-up. An object that stops moving produces no events and
no flow, and is reported lost after ``patience`` updates: an event camera has no evidence of it then.

Re-initialisation: an ``on_lost(batch_indices, t_us)`` callback (e.g. a detector or a user) is called
with the elements that became lost in this update (``(K,)`` int64) and their times ``(K,)`` int64 us;
it returns their new poses ``(K, 7)`` or ``None``. Returned poses come back in the
:class:`LossUpdate`; the caller re-initialises those tracker elements, and the detector restarts their
state.

Example:
    >>> import torch
    >>> from torchevtrack.loss import LossDetector
    >>> from torchevtrack.tracker import Quality
    >>> det = LossDetector(1, patience=2)
    >>> q = lambda s, n: Quality(torch.tensor([s]), torch.tensor([n]), torch.tensor([100]), torch.tensor([False]))
    >>> [bool(det(q(s, n), 2000 * i).lost) for i, (s, n) in enumerate([(2.0, 5), (0.1, 5), (0.1, 0)])]
    [False, False, True]
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable, NamedTuple

import numpy as np
import torch
from torch import nn

from torchevtrack.config import LossConfig
from torchevtrack.geometry import check_pose
from torchevtrack.kernels import kernel
from torchevtrack.metrics import FAIL_R_DEG, FAIL_T_M, FAIL_WINDOW, failure_index, per_pose_errors
from torchevtrack.stages import BufferViews

if TYPE_CHECKING:  # the tracker may import this module: no import cycle at run time
    from torchevtrack.tracker import Quality

__all__ = ["LOSS_DELAY_US", "LossArrays", "LossDetector", "LossUpdate", "compare_with_ground_truth", "loss_kernel",
           "loss_step", "update_times"]

LOSS_DELAY_US = 50_000
"""A failure counts as flagged in time when declared at most this long after its failure run began (issue targets)."""

OnLost = Callable[[torch.Tensor, torch.Tensor], "torch.Tensor | None"]


class LossUpdate(NamedTuple):
    """What :meth:`LossDetector.forward` reports.

    Attributes:
        confidence: ``(B,)`` float64 in ``[0, 1]``.
        lost: ``(B,)`` bool, after this update (before any re-initialisation).
        newly_lost: ``(B,)`` bool, became lost in this update.
        reinit_index: ``(K,)`` int64 elements the ``on_lost`` callback gave new poses for.
        reinit_pose: ``(K, 7)`` float64 those poses (validated); the caller resets the tracker with them.
    """

    confidence: torch.Tensor
    lost: torch.Tensor
    newly_lost: torch.Tensor
    reinit_index: torch.Tensor
    reinit_pose: torch.Tensor


def _array(x, dtype, B: int) -> np.ndarray:
    """``x`` (a tensor or array of ``B`` values) as a contiguous numpy array of ``dtype``."""
    return np.ascontiguousarray(np.asarray(x), dtype=dtype).reshape(B)


@kernel
def loss_kernel(score, flow_vectors, rejected, burst, t_us, reference, confidence, low_run, good_run, lost,
                lost_at_us, newly, score_threshold, min_flow_vectors, patience, recovery, ema):
    """One update of the loss rule (module docstring) for ``B`` elements, in place; releases the GIL.

    Shape: all arrays ``(B,)``. Inputs: ``score`` float64 (NaN or inf: no score), ``flow_vectors`` int64,
    ``rejected`` and ``burst`` bool, ``t_us`` int64. State, updated: ``reference``, ``confidence`` float64 (NaN
    reference: none yet), ``low_run``, ``good_run``, ``lost_at_us`` int64 (-1: no loss yet), ``lost`` bool.
    Output: ``newly`` bool, the elements that became lost. A ``burst`` element's state stays as it was.
    """
    for b in range(score.shape[0]):
        newly[b] = False
        if burst[b]:  # the burst guard dropped the window's events: no evidence either way
            continue
        s = score[b]
        has_score = math.isfinite(s)
        ref = reference[b]
        if math.isnan(ref) and has_score and s > 0.0:  # the first positive score starts the reference
            ref = s
        if not has_score:
            c_score = 1.0
        elif math.isnan(ref):
            c_score = 0.0
        else:
            c_score = min(max(s / ref, 0.0), 1.0)
        if min_flow_vectors > 0:
            c_flow = min(max(flow_vectors[b] / min_flow_vectors, 0.0), 1.0)
            few_flow = flow_vectors[b] < min_flow_vectors
        else:
            c_flow, few_flow = 1.0, False
        confidence[b] = 0.0 if rejected[b] else min(c_score, c_flow)
        low = rejected[b] or c_score < score_threshold or few_flow
        if not low and has_score:  # low scores never enter the reference
            ref = (1.0 - ema) * ref + ema * s
        reference[b] = ref
        if low:
            low_run[b] += 1
            good_run[b] = 0
        else:
            low_run[b] = 0
            good_run[b] += 1
        now = (lost[b] or low_run[b] >= patience) and not good_run[b] >= recovery
        if now and not lost[b]:
            newly[b] = True
            if lost_at_us[b] < 0:
                lost_at_us[b] = t_us[b]
        lost[b] = now


def update_times(t_us: int | torch.Tensor | np.ndarray, B: int) -> np.ndarray:
    """An update's time ``t_us`` (an integer for every element, or ``(B,)`` integers, microseconds) as a new ``(B,)``
    int64 array.

    Raises:
        TypeError: not integers. ValueError: an array of another size than ``B``.
    """
    t = np.asarray(t_us)
    if t.dtype.kind not in "iu":
        raise TypeError(f"t_us must be integer microseconds, got {t.dtype}")
    if t.ndim and t.size != B:
        raise ValueError(f"t_us must be one time or one per element ({B}), got shape {tuple(t.shape)}")
    return np.full(B, t, np.int64) if t.ndim == 0 else t.astype(np.int64).reshape(B)


class LossArrays(NamedTuple):
    """A :class:`LossDetector` as compiled kernels take it (:meth:`LossDetector.arrays`): numpy views of its buffers,
    written in place (``newly_lost``: the elements that became lost in the last update), and its rule's settings."""

    reference: np.ndarray
    confidence: np.ndarray
    low_run: np.ndarray
    good_run: np.ndarray
    lost: np.ndarray
    lost_at_us: np.ndarray
    newly_lost: np.ndarray
    score_threshold: float
    min_flow_vectors: int
    patience: int
    recovery: int
    ema: float


@kernel
def loss_step(a, score, flow_vectors, rejected, burst, t_us):
    """:func:`loss_kernel` on the detector's :class:`LossArrays` ``a`` in place; returns whether an element became
    lost (``a.newly_lost``). Inputs as for :func:`loss_kernel` (``score`` of any float dtype)."""
    loss_kernel(score, flow_vectors, rejected, burst, t_us, a.reference, a.confidence, a.low_run, a.good_run, a.lost,
                a.lost_at_us, a.newly_lost, a.score_threshold, a.min_flow_vectors, a.patience, a.recovery, a.ema)
    return a.newly_lost.any()


class LossDetector(BufferViews, nn.Module):
    """Declare tracking loss per batch element from the tracker's per-update quality.

    Args:
        batch_size: ``B``.
        score_threshold: an update whose score is below this fraction of the reference is low (in ``(0, 1]``).
        min_flow_vectors: an update with fewer flow vectors is low (0 disables the flow criterion).
        patience: consecutive low updates that make an element lost.
        recovery: consecutive confident updates that clear ``lost``.
        ema: rate of the reference's moving average, in ``(0, 1]``.
        initial_reference: reference score before any update (default: the first positive score).
        on_lost: optional re-initialisation callback, see the module docstring.
        (Defaults: the config section ``loss``, :class:`~torchevtrack.config.LossConfig`.)

    Buffers (all ``(B,)``):
        reference, confidence: float64; low_run, good_run: int64; lost: bool;
        lost_at_us: int64 time of the first loss declared since the last reset (-1: none);
        newly_lost: bool, the elements that became lost in the last update.

    ``forward(quality, t_us) -> LossUpdate`` with ``t_us`` an int or ``(B,)`` int64 update time (us); the quality's
    fields may be tensors or numpy arrays (the tracker gives its numpy ones).
    """

    reference: torch.Tensor
    confidence: torch.Tensor
    low_run: torch.Tensor
    good_run: torch.Tensor
    lost: torch.Tensor
    lost_at_us: torch.Tensor
    newly_lost: torch.Tensor

    def __init__(self, batch_size: int, score_threshold: float = LossConfig.score_threshold,
                 min_flow_vectors: int = LossConfig.min_flow_vectors, patience: int = LossConfig.patience,
                 recovery: int = LossConfig.recovery, ema: float = LossConfig.ema,
                 initial_reference: float | None = None, on_lost: OnLost | None = None) -> None:
        super().__init__()
        for name, v, lo in (("batch_size", batch_size, 1), ("min_flow_vectors", min_flow_vectors, 0),
                            ("patience", patience, 1), ("recovery", recovery, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        if not 0.0 < score_threshold <= 1.0:
            raise ValueError(f"score_threshold must be in (0, 1], got {score_threshold!r}")
        if not 0.0 < ema <= 1.0:
            raise ValueError(f"ema must be in (0, 1], got {ema!r}")
        if initial_reference is not None and not initial_reference > 0:
            raise ValueError(f"initial_reference must be a positive score or None, got {initial_reference!r}")
        if on_lost is not None and not callable(on_lost):
            raise TypeError(f"on_lost must be callable, got {type(on_lost).__name__}")
        self.batch_size = batch_size
        self.score_threshold, self.min_flow_vectors = float(score_threshold), min_flow_vectors
        self.patience, self.recovery, self.ema = patience, recovery, float(ema)
        self.initial_reference = initial_reference
        self.on_lost = on_lost
        B = batch_size
        self.register_buffer("reference", torch.zeros(B, dtype=torch.float64))
        self.register_buffer("confidence", torch.ones(B, dtype=torch.float64))
        self.register_buffer("low_run", torch.zeros(B, dtype=torch.int64))
        self.register_buffer("good_run", torch.zeros(B, dtype=torch.int64))
        self.register_buffer("lost", torch.zeros(B, dtype=torch.bool))
        self.register_buffer("lost_at_us", torch.zeros(B, dtype=torch.int64))
        self.register_buffer("newly_lost", torch.zeros(B, dtype=torch.bool))
        self.reset()

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Restart all elements, or those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices)."""
        if mask is None:
            mask = torch.ones(self.batch_size, dtype=torch.bool)
        mask = torch.as_tensor(mask)
        if mask.dtype == torch.bool:
            if mask.shape != (self.batch_size,):
                raise ValueError(f"mask must have shape ({self.batch_size},), got {tuple(mask.shape)}")
        elif mask.is_floating_point() or mask.ndim != 1:
            raise TypeError("mask must be a (B,) bool tensor or a 1-D tensor of batch indices")
        elif mask.numel() and (int(mask.min()) < 0 or int(mask.max()) >= self.batch_size):
            raise ValueError(f"mask indices must be in [0, {self.batch_size}), got {mask.tolist()}")
        ref = float("nan") if self.initial_reference is None else float(self.initial_reference)
        self.reference[mask] = ref
        self.confidence[mask] = 1.0
        self.low_run[mask] = 0
        self.good_run[mask] = 0
        self.lost[mask] = False
        self.lost_at_us[mask] = -1
        self.newly_lost[mask] = False

    def arrays(self) -> LossArrays:
        """The detector for compiled kernels (:func:`loss_step`): numpy views of the buffers (made again only when a
        buffer's storage changes, :class:`~torchevtrack.stages.BufferViews`) and the rule's settings."""
        views = self.buffer_views(("reference", "confidence", "low_run", "good_run", "lost", "lost_at_us",
                                   "newly_lost"))
        return LossArrays(*views, self.score_threshold, self.min_flow_vectors, self.patience, self.recovery, self.ema)

    def report(self, t_us: np.ndarray) -> LossUpdate:
        """The :class:`LossUpdate` of the last update at times ``t_us`` ``(B,)`` int64: the state's copies, and the
        ``on_lost`` callback's poses for the elements that became lost (called here, once per update; those
        elements restart)."""
        index = torch.empty(0, dtype=torch.int64)
        poses = torch.empty(0, 7, dtype=torch.float64)
        newly = self.newly_lost.clone()
        update = LossUpdate(self.confidence.clone(), self.lost.clone(), newly, index, poses)
        if self.on_lost is None or not bool(newly.any()):
            return update
        idx = newly.nonzero()[:, 0]
        out = self.on_lost(idx, torch.from_numpy(np.asarray(t_us, np.int64))[idx])
        if out is None:
            return update
        out = torch.as_tensor(out, dtype=torch.float64)
        if out.shape != (idx.numel(), 7):
            raise ValueError(f"on_lost must return poses of shape ({idx.numel()}, 7) or None, got {tuple(out.shape)}")
        poses = check_pose(out, "on_lost poses")
        lost_at = self.lost_at_us.clone()
        self.reset(idx)
        self.lost_at_us.copy_(lost_at)  # the first loss stays on record
        return update._replace(reinit_index=idx, reinit_pose=poses)

    def forward(self, quality: Quality, t_us: int | torch.Tensor) -> LossUpdate:
        B = self.batch_size
        fields = (quality.score, quality.flow_vectors, quality.rejected)
        if any(np.shape(f) != (B,) for f in fields):
            raise ValueError(f"quality fields must have shape ({B},), got {[tuple(np.shape(f)) for f in fields]}")
        t = update_times(t_us, B)
        burst = getattr(quality, "burst", None)
        burst = np.zeros(B, np.bool_) if burst is None else _array(burst, np.bool_, B)
        loss_step(self.arrays(), _array(quality.score, np.float64, B), _array(quality.flow_vectors, np.int64, B),
                  _array(quality.rejected, np.bool_, B), burst, t)
        return self.report(t)

    def extra_repr(self) -> str:
        return (f"batch_size={self.batch_size}, score_threshold={self.score_threshold}, "
                f"min_flow_vectors={self.min_flow_vectors}, patience={self.patience}, recovery={self.recovery}, "
                f"ema={self.ema}")


def compare_with_ground_truth(
    t_us: torch.Tensor,
    lost: torch.Tensor,
    poses: torch.Tensor,
    gt_t_us: torch.Tensor,
    gt_poses: torch.Tensor,
    *,
    symmetry_axis: torch.Tensor | None = None,
    max_t: float = FAIL_T_M,
    max_r_deg: float = FAIL_R_DEG,
    window: int = FAIL_WINDOW,
) -> dict:
    """Declared loss against the ground-truth failure rule (:func:`torchevtrack.metrics.failure_index`).

    Args:
        t_us: ``(N,)`` update times, us; lost: ``(N,)`` bool detector state per update;
        poses: ``(N, 7)`` tracker poses; gt_t_us, gt_poses: ``(G,)``, ``(G, 7)`` ground truth.
        symmetry_axis: ``(3,)`` object-frame axis of an untextured symmetric object, or None. With an axis the rule
            reads the rotation error modulo that axis (:func:`torchevtrack.metrics.rotation_error`), as the
            benchmark's held runs do: a spin about it changes no edge, so it is no failure a detector could see.
        max_t, max_r_deg, window: the failure rule (defaults: 7 cm, 40 deg, 50 samples).

    A declaration (``lost`` turning on) opens an episode that lasts until ``lost`` turns off (or the end). The
    failure is **detected** by the first episode still open when the failure run starts, or opened after it; an
    episode that closed before the failure run started is a false alarm (so is every episode of a run that never
    fails), and it does not count as detecting the failure.

    Returns:
        ``first_loss_us`` (first update declared lost, or None), ``first_failure_us`` (first sample of the
        first failure run, or None), ``delay_us`` (the detecting episode's declaration - failure; negative: declared
        before the failure run started and still lost then; None unless detected), ``missed`` (failed, no episode
        detected it), ``false_alarm`` (declared, never failed), ``declarations`` (updates where ``lost`` turned on),
        ``false_alarms`` (episodes closed before the first failure run started, all of them if none did),
        ``recoveries`` (updates where ``lost`` turned off) and ``tracked_us`` (time span of the compared updates).
        Updates outside the ground-truth time range are ignored.

    Example:
        >>> import torch
        >>> t = torch.arange(100, dtype=torch.int64) * 2000
        >>> gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(100, 7)
        >>> pred = gt.clone(); pred[40:, 0] += 0.1                  # 10 cm off from t = 80 ms on: failed there
        >>> lost = torch.zeros(100, dtype=torch.bool); lost[5:10] = True; lost[45:] = True
        >>> r = compare_with_ground_truth(t, lost, pred, t, gt)     # a false alarm at 10 ms, found lost at 90 ms
        >>> r["first_loss_us"], r["delay_us"], r["false_alarms"], r["missed"]
        (10000, 10000, 1, False)
    """
    lost = torch.as_tensor(lost)
    if lost.dtype != torch.bool or lost.ndim != 1:
        raise ValueError(f"lost must be a (N,) bool tensor, got {lost.dtype} {tuple(lost.shape)}")
    if lost.shape[0] != torch.as_tensor(t_us).shape[0]:
        raise ValueError(f"lost has {lost.shape[0]} updates but t_us has {torch.as_tensor(t_us).shape[0]}")
    e = per_pose_errors(t_us, poses, gt_t_us, gt_poses, symmetry_axis=symmetry_axis)
    lost = lost[e["keep"]]
    k = failure_index(e["te"], e["re"] if symmetry_axis is None else e["re_sym"], max_t=max_t, max_r_deg=max_r_deg,
                      window=window)
    first_failure = int(e["t_us"][k]) if k is not None else None
    flags = lost.to(torch.int8)
    rises = torch.cat((flags[:1], flags[1:] - flags[:-1])) if flags.numel() else flags
    opened, found = e["t_us"][rises > 0].tolist(), e["t_us"][rises < 0].tolist()  # each episode's start and end
    first_loss = opened[0] if opened else None
    closed = found + [None] * (len(opened) - len(found))  # None: still open at the end
    if first_failure is None:
        detecting, early = None, len(opened)
    else:  # the episodes closed by the failure run's start are false alarms; the next one detects it
        early = sum(c is not None and c <= first_failure for c in closed)
        detecting = opened[early] if early < len(opened) else None
    return {
        "first_loss_us": first_loss,
        "first_failure_us": first_failure,
        "delay_us": None if detecting is None else detecting - first_failure,
        "missed": first_failure is not None and detecting is None,
        "false_alarm": first_loss is not None and first_failure is None,
        "declarations": len(opened),
        "false_alarms": early,
        "recoveries": len(found),
        "tracked_us": int(e["t_us"][-1] - e["t_us"][0]) if e["t_us"].numel() else 0,
    }
