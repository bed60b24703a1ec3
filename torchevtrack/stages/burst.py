"""Burst guard: tell a window whose event count is far above the recent rate (a flash, a camera bump) before any
stage sees its events, so it can be dropped at O(1) cost instead of flooding the EROS, the flow and the template.

Rule per update and batch element (:func:`burst_update_`, one compiled step), for a window of ``n`` events over
``dt_us``:

* ``rate`` is an exponential moving average (weight ``ema``) of the events per second of the accepted windows,
  started by the first window that holds events (NaN before: windows without events leave it unset).
* the window is a **burst** when ``n > min_fraction * H * W`` (a fraction of the sensor's pixels, so ordinary
  motion, even fast and at 1280x720, never qualifies) **and** ``n > ratio * rate * dt`` (far above this
  element's recent rate). Before the rate has started nothing is a burst: with no history there is no normal
  to be far above, and a dense scene at the start (or after a reset) is the scene, not a flash (judging the first
  windows as bursts dropped the first 30 ms of a 640x480 sequence at 9.6 M events/s).
* a burst does not enter the rate, so a flash stays a flash. After ``max_run`` consecutive bursts the scene is
  taken to have changed for good: that window is accepted and restarts the rate at its own.

A burst window's events should reach no stage: :func:`keep_events` selects the others. With one element this is
a slice of length 0 (no copy); with several, one pass over the batch indices.

Example:
    >>> import torch
    >>> from torchevtrack.stages.burst import BurstGuard
    >>> g = BurstGuard(480, 640)
    >>> [bool(g(torch.tensor([n]), 2000)) for n in (4000, 5000, 2_000_000, 4500)]
    [False, False, True, False]
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torchevtrack.kernels import kernel
from torchevtrack.stages import BufferViews, batch_mask

__all__ = ["BurstGuard", "burst_update_", "keep_events"]


def burst_update_(rate: torch.Tensor, run: torch.Tensor, burst: torch.Tensor, n_events: torch.Tensor, dt_us: int,
                  *, floor: float, ratio: float, ema: float, max_run: int) -> None:
    """Judge one window of ``B`` elements by the rule of the module docstring, updating the state in place
    (one compiled step).

    Args:
        rate: ``(B,)`` float64 events/s of the accepted windows (NaN: none yet); run: ``(B,)`` int64 consecutive
            bursts before this window; burst: ``(B,)`` bool, receives this window's flags. All contiguous CPU
            tensors, written in place.
        n_events: ``(B,)`` integer events of each element in the window (tensor or array); dt_us: window length
            (us, > 0).
        floor: ``min_fraction * H * W`` events; ratio, ema, max_run: see :class:`BurstGuard`.

    Shape: ``(B,)`` everywhere.

    Raises:
        ValueError: state tensors of the wrong dtype or shape, ``n_events`` not integer ``(B,)``, or ``dt_us <= 0``.
            Nothing is written then.

    Example:
        >>> import torch
        >>> rate, run = torch.tensor([float("nan"), 1e6], dtype=torch.float64), torch.zeros(2, dtype=torch.int64)
        >>> burst = torch.zeros(2, dtype=torch.bool)
        >>> burst_update_(rate, run, burst, torch.tensor([500, 90_000]), 2000, floor=1000.0, ratio=10.0, ema=0.05,
        ...               max_run=25)
        >>> burst.tolist(), rate.tolist(), run.tolist()
        ([False, True], [250000.0, 1000000.0], [0, 1])
        >>> burst_update_(rate, run, burst, torch.tensor([90_000, 500]), 2000, floor=1000.0, ratio=10.0, ema=0.05,
        ...               max_run=25)  # a flash after a quiet window; the burst's element back to normal
        >>> burst.tolist(), run.tolist()
        ([True, False], [1, 0])
    """
    _check_state(rate, run, burst)
    _judge(rate.numpy(), run.numpy(), burst.numpy(), n_events, dt_us, floor, ratio, ema, max_run)


def _check_state(rate: torch.Tensor, run: torch.Tensor, burst: torch.Tensor) -> None:
    B = rate.shape
    if not (rate.dtype == torch.float64 and run.dtype == torch.int64 and burst.dtype == torch.bool
            and rate.ndim == 1 and run.shape == B and burst.shape == B
            and rate.is_contiguous() and run.is_contiguous() and burst.is_contiguous()):
        raise ValueError("rate, run and burst must be contiguous (B,) float64, int64 and bool tensors, got "
                         f"{rate.dtype} {tuple(rate.shape)}, {run.dtype} {tuple(run.shape)}, {burst.dtype} "
                         f"{tuple(burst.shape)}")


def _judge(rate: np.ndarray, run: np.ndarray, burst: np.ndarray, n_events, dt_us, floor, ratio, ema,
           max_run) -> None:
    """:func:`burst_update_` on numpy views of the state: checks ``n_events`` and ``dt_us``, then the kernel."""
    n = n_events.numpy() if isinstance(n_events, torch.Tensor) else np.asarray(n_events)
    if n.shape != rate.shape or n.dtype.kind not in "iu":
        raise ValueError(f"n_events must be an integer {rate.shape} tensor, got {n.dtype} {n.shape}")
    if not dt_us > 0:
        raise ValueError(f"dt_us must be positive, got {dt_us}")
    _burst_kernel(n if n.dtype == np.int64 else n.astype(np.int64), float(dt_us), rate, run, burst, float(floor),
                  float(ratio), float(ema), int(max_run))


@kernel
def _burst_kernel(n, dt_us, rate, run, burst, floor, ratio, ema, max_run):
    """The rule of the module docstring for each element in turn; the state arrays are written in place."""
    dt = dt_us * 1e-6
    for k in range(n.shape[0]):
        nk, r = float(n[k]), rate[k]
        fresh = np.isnan(r)
        flag = not fresh and nk > floor and nk > ratio * r * dt and run[k] < max_run
        burst[k] = flag
        if flag:
            run[k] += 1
        else:
            # the first window with events, or the new normal after a long run, restarts the rate
            if fresh or run[k] >= max_run:
                rate[k] = nk / dt if nk > 0 else np.nan
            else:
                rate[k] = (1 - ema) * r + ema * nk / dt
            run[k] = 0


def keep_events(b: torch.Tensor | None, n: int, burst: torch.Tensor) -> slice | torch.Tensor:
    """Which of a packed window's ``n`` events to keep given the elements' ``burst`` flags ``(B,)``.

    Returns a ``slice`` (``b`` is ``None``: one element; all or nothing, no copy) or an ``(n,)`` bool mask
    ``~burst[b]``; index every event field with it.
    """
    if b is None:
        return slice(0, 0) if bool(burst[0]) else slice(0, n)
    return ~burst[b.long()]


class BurstGuard(BufferViews, nn.Module):
    """Streaming burst detector for ``B`` event streams (module docstring).

    Args:
        height, width: sensor size (pixels); batch_size: ``B``.
        min_fraction: a burst holds more events than this fraction of the sensor's pixels (default 0.05: 15 k
            events at 640x480, 46 k at 1280x720, i.e. 7.7 M and 23 M events/s in 2 ms windows).
        ratio: ... and more than this many times the recent rate's count for the window (default 10).
        ema: weight of a window in the recent rate (default 0.05, ~20 windows).
        max_run: consecutive bursts after which a window is accepted as the new normal (default 25).

    Buffers:
        rate: ``(B,)`` float64 events/s (NaN before the first window with events); run: ``(B,)`` int64;
        burst: ``(B,)`` bool, the last window's flags.

    ``forward(n_events (B,) integer tensor or array, dt_us) -> burst (B,) bool`` (a new tensor); then
    :func:`keep_events` selects the events to pass on.
    """

    rate: torch.Tensor
    run: torch.Tensor
    burst: torch.Tensor

    def __init__(self, height: int, width: int, *, min_fraction: float = 0.05, ratio: float = 10.0,
                 ema: float = 0.05, max_run: int = 25, batch_size: int = 1):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size), ("max_run", max_run)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if not (min_fraction > 0 and ratio > 1 and 0 < ema <= 1):
            raise ValueError(f"need min_fraction > 0, ratio > 1 and 0 < ema <= 1, got {min_fraction}, {ratio}, {ema}")
        self.floor, self.ratio, self.ema, self.max_run = float(min_fraction) * height * width, float(ratio), \
            float(ema), max_run
        self.register_buffer("rate", torch.full((batch_size,), float("nan"), dtype=torch.float64))
        self.register_buffer("run", torch.zeros(batch_size, dtype=torch.int64))
        self.register_buffer("burst", torch.zeros(batch_size, dtype=torch.bool))

    def forward(self, n_events: torch.Tensor, dt_us: int) -> torch.Tensor:
        rate, run, burst = self._arrays()
        _judge(rate, run, burst, n_events, dt_us, self.floor, self.ratio, self.ema, self.max_run)
        return torch.from_numpy(burst.copy())

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """numpy views of the buffers ``rate, run, burst`` (:class:`~torchevtrack.stages.BufferViews`): converting the
        tensors at each window costs more than judging it."""
        return self.buffer_views(("rate", "run", "burst"), _check_state)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget the rate of every element, or of those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices)."""
        m = batch_mask(mask, self.rate.shape[0])
        self.rate.masked_fill_(m, float("nan"))
        self.run.masked_fill_(m, 0)
        self.burst.masked_fill_(m, False)

    def extra_repr(self) -> str:
        return f"floor={self.floor:.0f} events, ratio={self.ratio}, ema={self.ema}, max_run={self.max_run}, " \
               f"batch_size={self.rate.shape[0]}"
