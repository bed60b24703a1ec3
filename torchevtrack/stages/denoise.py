"""Background-activity and hot-pixel filter: drop events that no neighbour supports, and pixels that fire alone.

Rule, per event ``(x, y, t)`` of batch element ``b``, in time order (a compiled sequential kernel):

1. **Hot-pixel check period.** Each element counts the events of every pixel over periods of ``hot_period_us``
   (the first period starts at the element's first event). When an event falls at or after the end of the
   current period, the hot mask is recomputed from that period's counts ``n``: a pixel is **hot** when
   ``n >= hot_min_count`` and ``n > hot_ratio * max(m, 1)``, with ``m`` the mean count of its in-frame 3x3
   neighbours (itself excluded); then the counts restart and the period moves on to the one holding ``t``.
   Each recomputation is one pass over the frame (about 1 ms at 1280x720), once per period.
2. The event counts at its pixel (masked or not, so a hot pixel stays hot).
3. An event at a **hot** pixel is dropped and leaves no trace in the time surface below.
4. Otherwise it passes when one of its in-frame 3x3 neighbours (its own pixel excluded) holds a timestamp
   ``t_n`` with ``t - t_n <= dt_us`` (**support**), and its time is then written at its pixel
   (``last_us[b, y, x] = t``) whether it passes or not: the next event there finds it.

A moving edge fires along its length at once, so its events support each other; background-activity noise at
``r`` Hz per pixel finds support with probability about ``8 r dt_us``. Polarity is ignored. The state lives in
buffers and the rule depends only on the order of the events, so feeding a stream in windows of any size gives
the same decisions as feeding it at once (streaming-safe). Elements do not share state.

Example:
    >>> import torch
    >>> from torchevtrack.stages.denoise import BackgroundActivityFilter
    >>> f = BackgroundActivityFilter(8, 8, dt_us=1000)
    >>> x, y = torch.tensor([2, 3, 6]), torch.tensor([2, 2, 6])
    >>> f(x, y, torch.tensor([100, 300, 400])).tolist()  # (3, 2) has (2, 2) 200 us before; (6, 6) is alone
    [False, True, False]
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from torchevtrack.kernels import kernel
from torchevtrack.stages import NEVER, batch_mask
from torchevtrack.stages.eros import check_fields, check_times, events_inside, prepare_events

__all__ = ["BackgroundActivityFilter", "denoise_update_"]


def _check_state(last_us, count, hot, period_end) -> None:
    if not (isinstance(last_us, torch.Tensor) and last_us.dtype == torch.int64 and last_us.ndim == 3
            and last_us.is_contiguous()):
        raise ValueError("last_us must be a contiguous int64 (B, H, W) tensor")
    B = last_us.shape[0]
    if count.shape != last_us.shape or count.dtype != torch.int32 or not count.is_contiguous():
        raise ValueError(f"count must be a contiguous int32 {tuple(last_us.shape)} tensor")
    if hot.shape != last_us.shape or hot.dtype != torch.bool or not hot.is_contiguous():
        raise ValueError(f"hot must be a contiguous bool {tuple(last_us.shape)} tensor")
    if period_end.shape != (B,) or period_end.dtype != torch.int64:
        raise ValueError(f"period_end must be an int64 ({B},) tensor")


def denoise_update_(last_us: torch.Tensor, count: torch.Tensor, hot: torch.Tensor, period_end: torch.Tensor,
                    x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, b: torch.Tensor | None = None, *,
                    dt_us: int = 10_000, hot_period_us: int = 200_000, hot_ratio: float = 8.0,
                    hot_min_count: int = 10) -> torch.Tensor:
    """Apply the filter's rule (module docstring) to a packet of events, updating the state in place.

    Args:
        last_us: ``(B, H, W)`` int64 time of the newest non-hot event per pixel (:data:`~torchevtrack.stages.NEVER`
            where none); count: ``(B, H, W)`` int32 events per pixel in the current period; hot: ``(B, H, W)``
            bool mask of hot pixels; period_end: ``(B,)`` int64 end of the current period (``NEVER``: not started).
        x, y: ``(N,)`` integer pixels; t: ``(N,)`` int64 microseconds; b: ``(N,)`` batch index or ``None`` (all
            element 0); time order within each element.
        dt_us: support window (microseconds); hot_period_us, hot_ratio, hot_min_count: the hot-pixel rule.

    Shape: returns ``keep`` ``(N,)`` bool, True for the events that pass.

    Raises:
        TypeError / ValueError: bad fields (as :func:`~torchevtrack.stages.eros.prepare_events`), bad state, or
        non-positive parameters. Nothing is written then.
    """
    _check_state(last_us, count, hot, period_end)
    check_fields(x, y, b)
    check_times(t, x.shape)
    if not (dt_us > 0 and hot_period_us > 0 and hot_ratio > 0 and hot_min_count > 0):
        raise ValueError("dt_us, hot_period_us, hot_ratio and hot_min_count must be positive, got "
                         f"{dt_us}, {hot_period_us}, {hot_ratio}, {hot_min_count}")
    keep = torch.zeros(x.shape[0], dtype=torch.bool)
    if x.numel():
        bn = np.zeros(1, dtype=np.int64) if b is None else b.numpy()
        if not _denoise_kernel(last_us.numpy(), count.numpy(), hot.numpy(), period_end.numpy(), x.numpy(), y.numpy(),
                               t.numpy(), bn, b is not None, int(dt_us), int(hot_period_us), float(hot_ratio),
                               int(hot_min_count), keep.numpy()):
            B, H, W = last_us.shape
            prepare_events(x, y, b, H, W, B)  # raises the range error
    return keep


@kernel
def _hot_mask(count, hot, ratio, min_count):
    """Recompute one element's hot mask ``(H, W)`` from its period's counts, then zero the counts."""
    H, W = count.shape
    for v in range(H):
        for u in range(W):
            n = count[v, u]
            is_hot = False
            if n >= min_count:
                s, k = 0, 0
                for yy in range(max(v - 1, 0), min(v + 2, H)):
                    for xx in range(max(u - 1, 0), min(u + 2, W)):
                        if yy != v or xx != u:
                            s += count[yy, xx]
                            k += 1
                is_hot = n > ratio * max(s / max(k, 1), 1.0)
            hot[v, u] = is_hot
    count[:] = 0


@kernel
def _denoise_kernel(last, count, hot, period_end, x, y, t, b, batched, dt, period, ratio, min_count, keep):
    """The rule of the module docstring over the events in order; False, nothing written, if one lies outside."""
    B, H, W = last.shape
    if not events_inside(x, y, b, batched, B, H, W):
        return False
    never = NEVER
    for i in range(x.shape[0]):
        u, v, k, ti = x[i], y[i], b[i] if batched else 0, t[i]
        if period_end[k] == never:
            period_end[k] = ti + period
        elif ti >= period_end[k]:
            _hot_mask(count[k], hot[k], ratio, min_count)
            period_end[k] += ((ti - period_end[k]) // period + 1) * period
        count[k, v, u] += 1
        if hot[k, v, u]:
            continue
        ok = False
        for yy in range(max(v - 1, 0), min(v + 2, H)):
            for xx in range(max(u - 1, 0), min(u + 2, W)):
                tn = last[k, yy, xx]
                if (yy != v or xx != u) and tn != never and ti - tn <= dt:
                    ok = True
        keep[i] = ok
        last[k, v, u] = ti
    return True


class BackgroundActivityFilter(nn.Module):
    """Streaming background-activity and hot-pixel filter for ``B`` event streams (module docstring).

    Args:
        height, width: sensor size in pixels; batch_size: ``B``.
        dt_us: an event passes when a 3x3 neighbour fired at most this long before it (default 10 ms: 5 ms
            cost a slow regular sequence 1.4 cm / 14 deg, 20 ms let a noisy fast one be lost;
            ``tools/denoise_sequence.py``).
        hot_period_us: length of the periods over which hot pixels are counted (default 0.2 s).
        hot_ratio: a hot pixel fires more than this many times the mean of its neighbours (default 8) ...
        hot_min_rate_hz: ... and at least this often (default 50 Hz; ``hot_min_count`` is this times the period).

    Buffers:
        last_us: ``(B, H, W)`` int64; count: ``(B, H, W)`` int32; hot: ``(B, H, W)`` bool; period_end: ``(B,)``
        int64 (see :func:`denoise_update_`).

    ``forward(x, y, t, b=None)`` takes a packet of events and returns its ``keep`` mask ``(N,)`` bool; apply it to
    every field (``x[keep]``, ...) before the EROS and the flow.
    """

    last_us: torch.Tensor
    count: torch.Tensor
    hot: torch.Tensor
    period_end: torch.Tensor

    def __init__(self, height: int, width: int, *, dt_us: int = 10_000, hot_period_us: int = 200_000,
                 hot_ratio: float = 8.0, hot_min_rate_hz: float = 50.0, batch_size: int = 1):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size), ("dt_us", dt_us),
                        ("hot_period_us", hot_period_us)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if not (hot_ratio > 0 and hot_min_rate_hz > 0):
            raise ValueError(f"hot_ratio and hot_min_rate_hz must be positive, got {hot_ratio}, {hot_min_rate_hz}")
        self.dt_us, self.hot_period_us, self.hot_ratio = dt_us, hot_period_us, float(hot_ratio)
        self.hot_min_count = max(1, round(hot_min_rate_hz * hot_period_us * 1e-6))
        shape = (batch_size, height, width)
        self.register_buffer("last_us", torch.full(shape, NEVER, dtype=torch.int64))
        self.register_buffer("count", torch.zeros(shape, dtype=torch.int32))
        self.register_buffer("hot", torch.zeros(shape, dtype=torch.bool))
        self.register_buffer("period_end", torch.full((batch_size,), NEVER, dtype=torch.int64))

    def forward(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
        return denoise_update_(self.last_us, self.count, self.hot, self.period_end, x, y, t, b, dt_us=self.dt_us,
                               hot_period_us=self.hot_period_us, hot_ratio=self.hot_ratio,
                               hot_min_count=self.hot_min_count)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget the events and hot pixels of every element, or of those selected by ``mask`` (``(B,)`` bool or
        ``(K,)`` indices, see :func:`~torchevtrack.stages.batch_mask`)."""
        m = batch_mask(mask, self.last_us.shape[0])
        self.last_us.masked_fill_(m[:, None, None], NEVER)
        self.count.masked_fill_(m[:, None, None], 0)
        self.hot.masked_fill_(m[:, None, None], False)
        self.period_end.masked_fill_(m, NEVER)

    def extra_repr(self) -> str:
        B, H, W = self.last_us.shape
        return (f"height={H}, width={W}, dt_us={self.dt_us}, hot_period_us={self.hot_period_us}, "
                f"hot_ratio={self.hot_ratio}, hot_min_count={self.hot_min_count}, batch_size={B}")
