"""Step 1 of a streaming update and its observation in one compiled call: the pipeline thread's share of the update.

In streaming, a window's events arrive just before its update, so its intake cannot run ahead as it does in
``track``. The EROS and the time surface read only their own state and the events, and the observation
(:func:`~torchevtrack.stages.eros.canvas_observation`) reads only them, so while the calling thread runs the flow
(:func:`~torchevtrack.stages.intake.bind_intake` with ``surfaces=False``), the tracker's pipeline thread takes the
events into the EROS and the time surface and observes them under the canvas box of the template made ahead
(:class:`~torchevtrack.tracker.EventPoseTracker`). :func:`observe_step` is the EROS stage, the time surface stage and
``canvas_observation``, one after the other; its results equal theirs exactly (``tests/test_observe.py``).
"""

from __future__ import annotations

from typing import Callable

import numba
import numpy as np
import torch

from torchevtrack.stages.eros import (EROS, TimeSurface, _canvas_kernel, _check_fields, _check_times, _decay_table,
                                      _eros_kernel, _time_kernel, prepare_events)

__all__ = ["bind_observe", "observe_step"]


def observe_step(eros: EROS, time_surface: TimeSurface, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor,
                 b: torch.Tensor | None, box: torch.Tensor | None, canvas: int, t_now_us: torch.Tensor, *,
                 max_age_us: int = 0, recency_us: float = 0.0, rows: slice | None = None) -> torch.Tensor | None:
    """``eros(x, y, b, rows)``, ``time_surface(x, y, t, b, rows)``, then the observation under ``box``.

    Args:
        eros, time_surface: the stages (their ``rows``, default all ``B``); x, y, t, b: packed events as for
            their ``forward`` (``b`` counted from the first of ``rows``).
        box: ``(B, 3)`` float64 canvas boxes ``[cu, cv, side]`` (frame pixels), or ``None``: no observation.
        canvas, t_now_us, max_age_us, recency_us: as for :func:`~torchevtrack.stages.eros.canvas_observation`.

    Shape: returns the observation ``(B, canvas, canvas)`` float32, or ``None`` without a box.
    """
    _check_fields(x, y, b)
    _check_times(t, x.shape)
    B = eros.surface.shape[0] if rows is None else len(range(eros.surface.shape[0])[rows])
    if box is not None and (box.shape != (B, 3) or box.dtype != torch.float64):
        raise ValueError(f"box must be a float64 ({B}, 3) tensor, got {box.dtype} {tuple(box.shape)}")
    if t_now_us.shape != (B,) or t_now_us.dtype != torch.int64:
        raise ValueError(f"t_now_us must be an int64 ({B},) tensor, got {t_now_us.dtype} {tuple(t_now_us.shape)}")
    run = bind_observe(eros, time_surface, canvas=canvas, max_age_us=max_age_us, recency_us=recency_us, rows=rows)
    obs = run(x.numpy(), y.numpy(), t.numpy(), None if b is None else b.numpy(),
              None if box is None else box.numpy(), t_now_us.numpy())
    if obs is False:
        prepare_events(x, y, b, *eros.surface.shape[1:], B)  # raises the range error
    return None if obs is None else torch.from_numpy(obs)


def bind_observe(eros: EROS, time_surface: TimeSurface, *, canvas: int, max_age_us: int = 0, recency_us: float = 0.0,
                 rows: slice | None = None) -> Callable[..., np.ndarray | None | bool]:
    """:func:`observe_step` bound to the stages' state (numpy views of their ``rows``), unchecked, for the tracker's
    pipeline thread. Returns ``run(x, y, t, b, box, t_now_us)`` of numpy arrays (``b`` ``None``: all events in the
    first element), giving the observation (``None`` without a box) or ``False``, nothing written, if an event lies
    outside the surfaces."""
    surface = eros.surface if rows is None else eros.surface[rows]
    last = time_surface.last_us if rows is None else time_surface.last_us[rows]
    if surface.shape != last.shape:
        raise ValueError(f"the EROS and the time surface must have the same shape, got {tuple(surface.shape)} and "
                         f"{tuple(last.shape)}")
    s, last_np = surface.numpy(), last.numpy()
    lam, r = s.dtype.type(eros.decay ** (1.0 / eros.kernel_size)), eros.kernel_size // 2
    max_age_us, recency_us = int(max_age_us), float(recency_us)
    table = _decay_table(recency_us, max_age_us)
    none = np.zeros(1, dtype=np.int64)
    no_box = np.empty((0, 3))

    def run(x: np.ndarray, y: np.ndarray, t: np.ndarray, b: np.ndarray | None, box: np.ndarray | None,
            t_now_us: np.ndarray) -> np.ndarray | None | bool:
        obs = np.empty((s.shape[0], canvas, canvas) if box is not None else (0, canvas, canvas), dtype=np.float32)
        if not _observe_kernel(s, lam, r, last_np, x, y, t, none if b is None else b, b is not None,
                               no_box if box is None else box, t_now_us, max_age_us, recency_us, table, obs):
            return False
        return obs if box is not None else None
    return run


@numba.njit(cache=True, nogil=True)
def _observe_kernel(surface, lam, r, last, x, y, t, b, batched, box, t_now, max_age, tau, decay, out):
    """:func:`_eros_kernel` and :func:`_time_kernel`, then (if ``box`` has rows) :func:`_canvas_kernel` into ``out``;
    False, nothing written, if an event lies outside the surfaces."""
    if x.shape[0]:
        if not _eros_kernel(surface, x, y, b, batched, r, lam):
            return False
        _time_kernel(last, x, y, t, b, batched)
    if box.shape[0]:
        B, H, W = last.shape
        _canvas_kernel(surface, last.reshape(B, 1, H, W), box, t_now, max_age, tau, decay, out)
    return True
