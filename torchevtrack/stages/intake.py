"""Steps 1-2 of an update in one compiled call: a window's events into the EROS, its time surface and the flow.

The stages only read their own state and the events, so their order does not matter: :func:`intake_step`
runs the flow's kernel (which checks every event before it writes), then the EROS and the time surface kernels,
inside one call that releases the GIL. The tracker's pipeline thread runs it for the next window while the main
thread searches (:class:`~torchevtrack.tracker.EventPoseTracker`); one call keeps that thread from waiting for the
GIL between the stages. Its results equal those of the stage calls exactly (``tests/test_intake.py``).

The bound form (:func:`bind_intake`) can also run the flow alone, for a caller that takes the events into the EROS
and the time surface elsewhere meanwhile (:mod:`~torchevtrack.stages.observe`).
"""

from __future__ import annotations

from typing import Callable

import numba
import numpy as np
import torch

from torchevtrack.stages.eros import EROS, TimeSurface, _eros_kernel, _time_kernel, prepare_events
from torchevtrack.stages.flow import (FlowField, TripletFlow, _event_arrays, _events_in_range, _flow_packet,
                                      _range_error, _smooth)

__all__ = ["bind_intake", "intake_step"]


def intake_step(eros: EROS, time_surface: TimeSurface | None, flow: TripletFlow, x: torch.Tensor, y: torch.Tensor,
                t: torch.Tensor, p: torch.Tensor | None = None, b: torch.Tensor | None = None,
                rows: slice | None = None) -> FlowField:
    """``eros(x, y, b, rows)``, ``time_surface(x, y, t, b, rows)`` (unless it is ``None``) and
    ``flow(x, y, t, p, b, rows)``: the arguments, result and errors of the stages' ``forward`` (packed events:
    ``(N,)`` integer pixels ``x, y``, int64 microseconds ``t``, polarity ``p``, batch index ``b`` counted from the first
    of ``rows``), in one compiled call."""
    return FlowField(*(torch.from_numpy(a) for a in bind_intake(eros, time_surface, flow, rows)(x, y, t, p, b)))


def bind_intake(eros: EROS, time_surface: TimeSurface | None, flow: TripletFlow,
                rows: slice | None = None) -> Callable[..., FlowField]:
    """:func:`intake_step` bound to the stages' state (numpy views of their ``rows``, written in place at each call),
    for a caller that takes in a window every update (the tracker); ``time_surface`` ``None``: none is kept.
    Returns ``run(x, y, t, p, b, surfaces=True, checked=None)``, which checks the events as :func:`intake_step` does
    and gives its flow field as numpy arrays.
    With ``surfaces=False`` it runs the flow alone, leaving the EROS and the time surface to the caller. ``checked``,
    if given, is called with the events as numpy arrays ``(x, y, t, b)`` (``b`` ``None`` for one element) once every
    event is known to be in range, before anything is written (from there on the call cannot fail): the caller may
    start taking them into the EROS and the time surface elsewhere then."""
    surface = eros.surface if rows is None else eros.surface[rows]
    sae = flow.sae_padded if rows is None else flow.sae_padded[rows]
    B, C = sae.shape[:2]
    times = time_surface is not None
    last = (time_surface.last_us if rows is None else time_surface.last_us[rows]) if times else \
        torch.empty(B, 0, 0, dtype=torch.int64)
    if surface.shape[0] != B or last.shape[0] != B:
        raise ValueError(f"the EROS, the time surface and the flow must hold the same elements, got "
                         f"{surface.shape[0]}, {last.shape[0]} and {B}")
    G = flow.n_blocks
    s, last_np, sae_np = surface.numpy(), last.numpy(), sae.numpy()
    lam, r = s.dtype.type(eros.decay ** (1.0 / eros.kernel_size)), eros.kernel_size // 2
    matching = flow.params

    def _range_errors(x, y, t, p, b):
        prepare_events(x, y, b, *surface.shape[1:], B)  # the EROS stage's range error
        _range_error(tuple(sae.shape[:2]) + (flow.height, flow.width), x, y, t, p, b)  # the flow's (polarity)

    def run(x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None = None,
            b: torch.Tensor | None = None, surfaces: bool = True,
            checked: Callable[..., object] | None = None) -> FlowField:
        xn, yn, tn, pn, bn, batched = _event_arrays(C, x, y, t, p, b)  # checks the fields as the EROS stage does
        if checked is not None:
            if not _events_in_range(xn, yn, pn, bn, C, batched, B, flow.height, flow.width):
                _range_errors(x, y, t, p, b)
            checked(xn, yn, tn, bn if batched else None)
        out, uv = np.zeros((B, G, 2), dtype=np.float32), np.empty((B, G, 2), dtype=np.float32)
        valid, count = np.empty((B, G), dtype=np.bool_), np.empty((B, G), dtype=np.int64)
        if not _intake_kernel(s, lam, r, last_np, surfaces, surfaces and times, sae_np, xn, yn, tn, pn, bn, C, batched,
                              *matching, out, uv, valid, count):
            _range_errors(x, y, t, p, b)
        if flow.smooth:
            out, uv = (a.numpy() for a in _smooth(torch.from_numpy(out), torch.from_numpy(uv), torch.from_numpy(valid),
                                                  flow.gy, flow.gx))
        return FlowField(uv, out, valid, count)
    return run


@numba.njit(cache=True, nogil=True)
def _intake_kernel(surface, lam, r, last, surfaces, times, sae, x, y, t, p, b, C, batched, dirs, pad, dt_max_us,
                   tol, chunk, block_x, block_y, G, min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv,
                   valid, count):
    """:func:`_flow_packet`, then (``surfaces``) :func:`_eros_kernel` and (``times``) :func:`_time_kernel` if every
    event was in range (False: nothing written)."""
    ok = _flow_packet(sae, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, chunk, block_x, block_y, G,
                      min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv, valid, count)
    if ok and surfaces and x.shape[0]:
        ok = _eros_kernel(surface, x, y, b, batched, r, lam) and (not times or _time_kernel(last, x, y, t, b, batched))
    return ok
