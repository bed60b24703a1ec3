"""The pipeline stages (see the README's pipeline table) and what they share: batch-element selection and the
bilinear taps of the template canvas (sampled by the template stage and by the EROS observation)."""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch

__all__ = ["NEVER", "batch_mask"]

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


@functools.lru_cache(maxsize=64)
def periods(batch_size: int, dt: float) -> np.ndarray:
    """The update period ``dt`` (seconds) of every element as a read-only float64 ``(B,)`` array, for the compiled
    steps that take one per element (made once per ``(B, dt)``: an update needs it several times)."""
    out = np.full(batch_size, float(dt))
    out.flags.writeable = False
    return out


@numba.njit(cache=True, nogil=True)
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
