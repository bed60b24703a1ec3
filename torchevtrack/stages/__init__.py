"""The pipeline stages (see the README's pipeline table) and what they share: batch-element selection, the numpy
views of a module's buffers its compiled kernels take, and the bilinear taps of the template canvas (sampled by the
template stage and by the EROS observation)."""

from __future__ import annotations

import functools
import math
from typing import Callable

import numpy as np
import torch

from torchevtrack.kernels import kernel

__all__ = ["NEVER", "BufferViews", "batch_mask"]

NEVER = -(2 ** 62)
"""Time of a pixel that never fired, in the time surfaces (int64 microseconds): the flow's SAE and the
:class:`~torchevtrack.stages.eros.TimeSurface`."""


def batch_mask(mask: torch.Tensor | None, batch_size: int) -> torch.Tensor:
    """Select batch elements: ``None`` (all), a ``(B,)`` bool mask or ``(K,)`` integer indices.

    Used by the stages' masked ``reset``: only the selected elements restart.

    Shape: returns ``(B,)`` bool.

    Raises:
        TypeError: not a bool or integer tensor.
        ValueError: a bool mask of the wrong shape, or an index outside ``[0, B)``.
    """
    if mask is None:
        return torch.ones(batch_size, dtype=torch.bool)
    mask = torch.as_tensor(mask)
    if mask.dtype == torch.bool:
        if mask.shape != (batch_size,):
            raise ValueError(f"mask must have shape ({batch_size},), got {tuple(mask.shape)}")
        return mask
    if mask.is_floating_point() or mask.is_complex() or mask.ndim != 1:
        raise TypeError(f"mask must be a ({batch_size},) bool tensor or a 1-D tensor of batch indices, "
                        f"got {mask.dtype} {tuple(mask.shape)}")
    if mask.numel() and (int(mask.min()) < 0 or int(mask.max()) >= batch_size):
        raise ValueError(f"mask indices must be in [0, {batch_size}), got {mask.tolist()}")
    return torch.zeros(batch_size, dtype=torch.bool).index_fill_(0, mask.long(), True)


class BufferViews:
    """Mixin for an ``nn.Module`` whose compiled kernels update its buffers in place through numpy views.

    :meth:`buffer_views` makes the views once and again whenever a buffer's storage changes (a new tensor assigned,
    ``.to``, ``.float``, ``share_memory``; ``load_state_dict`` copies in place and keeps them): making a view costs
    about 2 us, more than some of these kernels' work per update. A copy or a pickle leaves the views out (a copy's
    would not share its buffers) and makes its own.
    """

    _views: tuple | None = None

    def buffer_views(self, names: tuple[str, ...],
                     check: Callable[..., None] | None = None) -> tuple[np.ndarray, ...]:
        """Numpy views of the buffers ``names``, in that order; ``check(*tensors)`` runs whenever they are made."""
        tensors = tuple(self._buffers[n] for n in names)
        key = tuple(t.data_ptr() for t in tensors)
        if self._views is None or self._views[0] != key:
            if check is not None:
                check(*tensors)
            self._views = key, tuple(t.numpy() for t in tensors)
        return self._views[1]

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_views"] = None
        return state


@functools.lru_cache(maxsize=64)
def periods(batch_size: int, dt: float) -> np.ndarray:
    """The update period ``dt`` (seconds) of every element as a read-only float64 ``(B,)`` array, for the compiled
    steps that take one per element (made once per ``(B, dt)``: an update needs it several times)."""
    out = np.full(batch_size, float(dt))
    out.flags.writeable = False
    return out


@kernel
def canvas_taps(c, step, N, n):
    """Bilinear taps along one axis of the ``N`` canvas pixels centred at ``c + (j + 0.5 - N / 2) step`` in an
    axis of ``n`` pixels: the two indices, clamped into ``[0, n)``, and their weights, 0 for a tap outside.

    Shape: returns ``i0, i1`` ``(N,)`` int64 and ``a0, a1`` ``(N,)`` float64.
    """
    i0, i1, a0, a1 = np.empty(N, np.int64), np.empty(N, np.int64), np.empty(N), np.empty(N)
    for j in range(N):
        x = c + (j + 0.5 - N / 2) * step
        k = math.floor(x)
        f = x - k
        i0[j], i1[j] = min(max(k, 0), n - 1), min(max(k + 1, 0), n - 1)
        a0[j], a1[j] = (1 - f) if 0 <= k < n else 0.0, f if -1 <= k < n - 1 else 0.0
    return i0, i1, a0, a1
