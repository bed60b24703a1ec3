"""Stage 2: event optical flow by spatio-temporal triplet matching and per-block registration.

Surface of active events (SAE): the last event time (int64 us) per pixel, optionally one channel per
polarity; a pixel that never fired holds :data:`NEVER`.

Triplets. For an event ``e0 = (p0, t0)`` and an offset ``d = (dx, dy)``, ``|dx|, |dy| <= D``, ``d != 0``
(``D = 2``: 24 directions), let ``p1 = p0 + d``, ``p2 = p0 + 2 d`` and ``t1, t2`` their SAE times,
``dt01 = t0 - t1``, ``dt12 = t1 - t2``. The triplet is accepted when ``0 < dt01 < dt_max``,
``dt12 > 0`` and ``|1 - dt12 / dt01| < tol``; its flow sample is ``F = (p0 - p2) / (t0 - t2) =
-2 d / (dt01 + dt12)`` pixel/s (an edge moving along +x at ``v`` px/s gives ``(+v, 0)``).

Crossing onsets (``onset_us > 0``; off by default, config ``flow.onset_us``). An edge crossing a pixel fires
one event per contrast threshold, spread over the crossing, and each of them matched against its neighbours'
*newest* times mixes early and late parts of their crossings: the triplets read the edge 5-18 % fast on simulated
sequences, leading edges more than trailing ones (docs/notebook.md, 2026-12-05). With ``onset_us > 0`` only an
event whose pixel was silent for more than ``onset_us`` (its previous event, matched or not, is older) is matched
and written into the SAE, which then holds each pixel's newest crossing onset; every event renews the pixel's
last-event time (buffer ``last_padded``). A pixel that keeps firing (a hot pixel, flicker) stays silent for the
flow. ``onset_us = 0`` matches every event (the paper's SAE).

Which SAE an event sees (exact, causal): the SAE as it was before the packet, updated with every
*strictly earlier* event of the packet (packed order, same batch element, same polarity channel). The
matching is that per-event loop itself, compiled (numba): each event looks up its ``2 K`` pixels,
keeps its triplets, then writes ``SAE[p0] = max(SAE[p0], t0)``. Pixels outside the image never fired
(the SAE is stored padded with :data:`NEVER`).

Registration. The image is cut into ``block x block`` pixel RoIs (the last row / column may be
partial). Each sample belongs to the block of its event pixel ``p0``. A block with at least
``min_samples`` samples gets one flow ``F`` chosen among its samples ``M`` minimising
``C(F) = sum_i min_{F_ic in M_i} |F - F_ic|`` (``M_i``: samples of event ``i``; Euclidean norm).
Ties: a straight edge supports a whole line of flows (aperture problem) and all of them cost about
alike, so among the near-optimal candidates, ``C(F) <= C_min + tie_tol * n_events * |F|``, the one
closest to all samples (least ``sum_j |F - F_j|`` over the block's samples, a geometric median) is
taken; for a straight edge the samples lie symmetrically about the normal flow, which is then chosen.
``tie_tol = 0`` keeps exact ties only (then the same rule breaks them). A block with more than
``max_candidates`` samples is evaluated on a deterministic subset: every ``s``-th event of the block
(packed order, ``s = ceil(samples / max_candidates)``) with all its samples, then the first
``max_candidates`` samples of those.

Output estimate. Every triplet sample is parallel to its offset ``d``, so the registered candidate
(``estimate="register"``, the paper) has one of the ``(2D+1)^2 - 1`` directions: up to ~13 degrees off
for D = 2. The default ``estimate="normal"`` keeps the registration to pick the inlier events (whose
nearest candidate is within ``inlier * |F|`` of the registered ``F``) and fits the time-surface
gradient ``g`` (s/px) to all their samples, each sample being the line ``F_j . g = 1``; the block flow
is the normal flow ``g / |g|^2``. For an edge (the usual case in a block) that is the flow component
the events determine, with continuous direction; for 2-D texture it is an average normal flow.

Events are packed as 1-D tensors ``x``, ``y`` (pixel column / row), ``t`` (int64 us), ``p`` (``{0, 1}``)
and ``b`` (batch index, or ``None`` for all-zero); within each batch element the packed order is time
order.

Memory: the matching needs no temporaries beyond its output (12 bytes per possible sample, ``K`` per
event). :class:`TripletFlow` matches a packet longer than ``chunk`` events (a burst) chunk by chunk, so
that buffer stays bounded, then registers all samples together; the samples, the SAE and the flow
field equal those of one pass exactly (the samples themselves are few: about 0.5 per event on noise
bursts).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch
from numba.cpython.unsafe.numbers import trailing_zeros
from torch import nn

from torchevtrack.config import FlowConfig
from torchevtrack.kernels import kernel
from torchevtrack.prefetch import AHEAD, prefetch
from torchevtrack.stages import NEVER, batch_mask
from torchevtrack.stages.eros import check_fields, check_times, prepare_events

__all__ = [
    "NEVER",
    "FlowField",
    "FlowParams",
    "TripletFlow",
    "block_grid",
    "event_arrays",
    "events_in_range",
    "flow_packet",
    "range_error",
    "register_blocks",
    "sae_update",
    "sae_update_",
    "triplet_samples",
]

class FlowField(NamedTuple):
    """Sparse flow on the block grid of ``G = Gy * Gx`` RoIs (row-major, block ``(gy, gx)`` is ``gy * Gx + gx``).

    Attributes:
        uv: ``(B, G, 2)`` float32 pixel ``(u, v)`` the flow refers to: for a valid block the mean event
            pixel of its inlier samples (see :func:`register_blocks`), else the centre of the block's
            in-image area.
        flow: ``(B, G, 2)`` float32 flow in pixel/s (0 where not valid).
        valid: ``(B, G)`` bool, the block had at least ``min_samples`` samples.
        count: ``(B, G)`` int64 number of triplet samples in the block.
    """

    uv: torch.Tensor
    flow: torch.Tensor
    valid: torch.Tensor
    count: torch.Tensor


def _directions(D: int) -> torch.Tensor:
    r = torch.arange(-D, D + 1)
    d = torch.stack(torch.meshgrid(r, r, indexing="xy"), -1).reshape(-1, 2)
    return d[(d != 0).any(1)]  # (K, 2) as (dx, dy)


def _check_sae(sae: torch.Tensor) -> None:
    if not isinstance(sae, torch.Tensor) or sae.dtype != torch.int64 or sae.ndim != 4 or sae.shape[1] not in (1, 2):
        raise ValueError("sae must be an int64 (B, C, H, W) tensor with C in {1, 2}, got "
                         f"{getattr(sae, 'dtype', type(sae).__name__)} {tuple(getattr(sae, 'shape', ()))}")


def _check_time_polarity(t, p, shape: torch.Size, C: int) -> None:
    """``t`` int64 microseconds and, with two SAE channels (``C = 2``), an integer ``p``, both of ``shape``."""
    check_times(t, shape)
    if C == 2 and (not isinstance(p, torch.Tensor) or p.shape != shape or p.is_floating_point()):
        raise TypeError(f"p must be an integer tensor with the shape of x {tuple(shape)}")


def _prepare(sae: torch.Tensor, x, y, t, p, b):
    _check_sae(sae)
    B, C, H, W = sae.shape
    xi, yi, bi = prepare_events(x, y, b, H, W, B)
    _check_time_polarity(t, p, xi.shape, C)
    if C == 1:
        ci = torch.zeros_like(xi)
    else:
        ci = p.long()
        if ci.numel() and bool(((ci < 0) | (ci > 1)).any()):
            raise ValueError("p must be in {0, 1}")
    return xi, yi, bi * C + ci


_NONE = np.zeros(1, dtype=np.int64)


def event_arrays(C: int, x, y, t, p, b):
    """The packed events of :meth:`TripletFlow.forward` as numpy arrays for the compiled kernels (views where the
    dtypes allow), for an SAE of ``C`` channels. Their types and shapes are checked here, with the errors
    ``forward`` raises (TypeError, ValueError); their ranges are not (:func:`events_in_range`, :func:`range_error`).

    Returns ``(x, y, t, p, b, batched)``: the event of index ``i`` updates the SAE plane ``b[i] C + p[i]``;
    ``p`` (only read when ``C = 2``) and ``b`` (only read when ``batched``) may be placeholders."""
    check_fields(x, y, b)
    _check_time_polarity(t, p, x.shape, C)
    pn = _NONE if C == 1 else _index_array(p)
    bn = _NONE if b is None else _index_array(b)
    return _index_array(x), _index_array(y), t.numpy(), pn, bn, b is not None


def range_error(shape: tuple[int, int, int, int], x, y, t, p, b):
    """Raise the ValueError :meth:`TripletFlow.forward` raises for the packed events ``x, y, t, p, b`` (tensors, as
    given to it) that do not fit an SAE of ``shape`` ``(B, C, H, W)``: it names the first field out of range. For
    a caller whose compiled call found such an event (:func:`events_in_range` or :func:`flow_packet` False)."""
    _prepare(torch.empty(shape, dtype=torch.int64), x, y, t, p, b)


_INDEX_DTYPES = (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8)


def _index_array(v: torch.Tensor) -> np.ndarray:
    """A numpy view of an integer tensor the kernels index with (other integer types, and bool, as int64)."""
    return (v if v.dtype in _INDEX_DTYPES else v.long()).numpy()


@kernel
def events_in_range(x, y, p, b, C, batched, B, H, W):
    """Every event of :func:`event_arrays` inside ``[0, W) x [0, H)``, its batch index in ``[0, B)`` (when
    ``batched``) and (``C = 2``) its polarity in ``{0, 1}``: the events fit an SAE ``(B, C, H, W)``. Compiled."""
    for i in range(x.shape[0]):
        if x[i] < 0 or x[i] >= W or y[i] < 0 or y[i] >= H:
            return False
        if batched and (b[i] < 0 or b[i] >= B):
            return False
        if C == 2 and (p[i] < 0 or p[i] > 1):
            return False
    return True


def sae_update_(sae: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None,
                b: torch.Tensor | None = None) -> torch.Tensor:
    """In place: ``sae[b, c, y, x] = max(sae, t)`` per event (``c = p`` if two channels, else 0); returns ``sae``.

    Shape:
        sae: ``(B, C, H, W)`` int64 us, ``C`` in ``{1, 2}``; x, y, t, p, b: ``(N,)``.
    """
    _check_sae(sae)
    check_fields(x, y, b)
    B, C, H, W = sae.shape
    _check_time_polarity(t, p, x.shape, C)
    none = np.zeros(1, dtype=np.int64)
    if x.numel() and not _sae_kernel(sae.view(B * C, H, W).numpy(), x.numpy(), y.numpy(), t.numpy(),
                                     none if C == 1 else p.numpy(), none if b is None else b.numpy(), C, b is not None):
        _prepare(sae, x, y, t, p, b)  # raises the range error (the kernel checks before it writes)
    return sae


@kernel
def _sae_kernel(sae, x, y, t, p, b, C, batched):
    """``sae[b C + p, y, x] = max(., t)`` per event; returns False, untouched, if one lies outside."""
    planes, H, W = sae.shape
    for i in range(x.shape[0]):
        c = (b[i] if batched else 0) * C + (p[i] if C == 2 else 0)
        if x[i] < 0 or x[i] >= W or y[i] < 0 or y[i] >= H or c < 0 or c >= planes or (C == 2 and p[i] > 1):
            return False
    for i in range(x.shape[0]):
        c = (b[i] if batched else 0) * C + (p[i] if C == 2 else 0)
        sae[c, y[i], x[i]] = max(sae[c, y[i], x[i]], t[i])
    return True


def sae_update(sae, x, y, t, p, b=None) -> torch.Tensor:
    """Out-of-place :func:`sae_update_`."""
    return sae_update_(sae.clone(), x, y, t, p, b)


def _pad_sae(sae: torch.Tensor, pad: int) -> torch.Tensor:
    B, C, H, W = sae.shape
    out = torch.full((B, C, H + 2 * pad, W + 2 * pad), NEVER, dtype=torch.int64)
    out[:, :, pad:pad + H, pad:pad + W] = sae
    return out


def _direction_array(D: int) -> np.ndarray:
    """:func:`_directions` as a numpy array, cached."""
    dirs = _DIRECTIONS.get(D)
    if dirs is None:
        dirs = _DIRECTIONS[D] = _directions(D).numpy()
    return dirs


_DIRECTIONS: dict[int, np.ndarray] = {}


@kernel
def _match_packet(sae, last, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, onset_us, chunk):
    """Triplet samples of a packet of events (:func:`event_arrays`: event ``i`` in SAE plane ``b[i] C + p[i]``)
    against the padded SAE ``(B, Cs, Hp, Wp)``, which they update in place as they go (each event looks up, then
    writes: the module docstring's "strictly earlier"), ``chunk`` events at a time (a buffer of ``chunk K``
    samples). With ``onset_us > 0`` only crossing onsets match and write, and ``last`` (the SAE's shape: each
    pixel's newest event time) takes every event; with ``onset_us = 0`` ``last`` is not read (any array). Returns
    ``event (S,)`` (index into the packet), ``flow (S, 2)`` float32 and ``ok``: False, nothing matched or written, if
    an event lies outside the SAE."""
    B, Cs, Hp, Wp = sae.shape
    planes = B * Cs
    sae3 = sae.reshape(planes, Hp, Wp)
    n, K = x.shape[0], dirs.shape[0]
    size = min(n, chunk) * K
    event, flow = np.empty(size, dtype=np.int64), np.empty((size, 2), dtype=np.float32)
    if not events_in_range(x, y, p, b, C, batched, planes // C, Hp - 2 * pad, Wp - 2 * pad):
        return event[:0], flow[:0], False
    if n <= chunk:
        s = _triplet_kernel(sae3, last, x, y, t, p, b, C, batched, np.int64(0), n, dirs, pad, dt_max_us, tol, onset_us,
                            event, flow)
        return event[:s], flow[:s], True
    out_event, out_flow = np.empty(size, dtype=np.int64), np.empty((size, 2), dtype=np.float32)
    S = 0
    for start in range(0, n, chunk):
        s = _triplet_kernel(sae3, last, x, y, t, p, b, C, batched, start, min(n, start + chunk), dirs, pad, dt_max_us,
                            tol, onset_us, event, flow)
        if S + s > out_event.shape[0]:  # grow
            grown = max(S + s, 2 * out_event.shape[0])
            out_event = np.concatenate((out_event[:S], np.empty(grown - S, dtype=np.int64)))
            out_flow = np.concatenate((out_flow[:S], np.empty((grown - S, 2), dtype=np.float32)))
        out_event[S:S + s], out_flow[S:S + s] = event[:s], flow[:s]
        S += s
    return out_event[:S], out_flow[:S], True


_WORD = 63
"""Directions per bit mask of :func:`_triplet_kernel` (bits 0..62 of an int64)."""

_LINE = 8
"""SAE entries (int64) per 64-byte cache line."""


@kernel
def _triplet_kernel(sae, last, x, y, t, p, b, C, batched, start, stop, dirs, pad, dt_max_us, tol, onset_us, event,
                    flow):
    """Per event ``i`` in ``start:stop`` that starts a crossing (always, with ``onset_us = 0``; else its pixel's
    entry of ``last`` is more than ``onset_us`` older, and ``last`` takes every event): look up ``p0 + d`` and
    ``p0 + 2 d`` for every direction ``d``, keep the triplets that pass, then write the event into the SAE (plane
    ``b C + p``). Returns the number of samples written to ``event``, ``flow``.

    The tests of an event's ``K`` directions run as one vector loop into a bit mask (:func:`_pass_mask`), then
    the samples of the set bits are written in direction order (:func:`_emit`). With ``K <= 63`` (one mask) an
    event's samples are written one event later, so that the branches over them do not hold up the next
    event's lookups.

    The lookups of event ``i + AHEAD`` (its ``(4 D + 1)^2`` neighbourhood, ``D = pad / 2``) are prefetched while event
    ``i`` is matched: a noise event's neighbourhood lies out of every cache, and without the hint each event waits
    for its own reads (3-6x the time of an event on an edge; the samples are the same)."""
    n_planes, Hp, Wp = sae.shape
    flat = sae.reshape(n_planes * Hp * Wp)
    seen = last.reshape(last.size)  # read only with onset_us > 0, then laid out as sae
    K = dirs.shape[0]
    off1 = np.empty(K, dtype=np.int64)
    fx, fy = np.empty(K), np.empty(K)
    for k in range(K):
        off1[k] = dirs[k, 1] * Wp + dirs[k, 0]
        fx[k], fy[k] = -2.0 * dirs[k, 0], -2.0 * dirs[k, 1]
    lag = K <= _WORD
    s = 0
    at_prev = t_prev = m_prev = 0
    for i in range(start, stop):
        j = i + AHEAD
        if j < stop:
            cj = (b[j] if batched else 0) * C + (p[j] if C == 2 else 0)
            corner = (cj * Hp + y[j]) * Wp + x[j]  # the padded neighbourhood's top-left: pad rows and columns back
            for r in range(2 * pad + 1):
                row = corner + r * Wp
                for col in range(0, 2 * pad, _LINE):  # then the row's last entry, below
                    prefetch(flat, row + col)
                prefetch(flat, row + 2 * pad)
        c = (b[i] if batched else 0) * C + (p[i] if C == 2 else 0)
        at = (c * Hp + y[i] + pad) * Wp + x[i] + pad
        onset = True
        if onset_us > 0:
            onset = t[i] - seen[at] > onset_us
            seen[at] = max(seen[at], t[i])
        if lag:
            m = _pass_mask(flat, at, t[i], off1, 0, K, dt_max_us, tol) if onset else 0
            s = _emit(flat, at_prev, t_prev, i - 1, off1, 0, fx, fy, tol, m_prev, event, flow, s)
            at_prev, t_prev, m_prev = at, t[i], m
        elif onset:
            for lo in range(0, K, _WORD):
                m = _pass_mask(flat, at, t[i], off1, lo, min(K, lo + _WORD), dt_max_us, tol)
                s = _emit(flat, at, t[i], i, off1, lo, fx, fy, tol, m, event, flow, s)
        if onset:
            flat[at] = max(flat[at], t[i])
    return _emit(flat, at_prev, t_prev, stop - 1, off1, 0, fx, fy, tol, m_prev, event, flow, s)


@kernel(inline="always")
def _pass_mask(flat, at, t0, off1, lo, hi, dt_max_us, tol):
    """Bit ``k - lo`` set: direction ``k`` in ``lo:hi`` may pass for the event at SAE index ``at``, time ``t0``
    (the exact integer tests, and ``|dt12 - dt01| <= tol' dt01`` with ``tol'`` a hair above ``tol``: a superset of
    the passing directions, whose float test :func:`_emit` applies)."""
    tol_up = tol * (1.0 + 2.0 ** -30) + 2.0 ** -40
    m = 0
    for k in range(lo, hi):
        # unsigned: an index needs no negative wrap-around, 0 < dt01 < dt_max is one comparison
        t1 = flat[np.uint64(at + off1[k])]
        dt01 = t0 - t1
        dt12 = t1 - flat[np.uint64(at + 2 * off1[k])]
        good = (np.uint64(dt01 - 1) < np.uint64(dt_max_us - 1)) & (dt12 > 0) & (abs(dt12 - dt01) <= tol_up * dt01)
        m |= np.int64(good) << (k - lo)
    return m


@kernel(inline="always")
def _emit(flat, at, t0, i, off1, lo, fx, fy, tol, m, event, flow, s):
    """Write the samples of event ``i`` (SAE index ``at``, time ``t0``) for the directions ``lo + bit`` of mask
    ``m`` that pass ``|1 - dt12 / dt01| < tol``, from ``event[s]``, ``flow[s]`` on; returns the new ``s``. The
    event's own SAE write, if already done, is at ``at``, which is none of its lookups."""
    while m:
        k = lo + trailing_zeros(m)
        m &= m - 1
        t1 = flat[at + off1[k]]
        dt01 = t0 - t1
        dt12 = t1 - flat[at + 2 * off1[k]]
        if abs(1.0 - dt12 / dt01) < tol:
            span = (dt01 + dt12) * 1e-6  # t0 - t2, seconds
            event[s] = i
            flow[s, 0] = fx[k] / span
            flow[s, 1] = fy[k] / span
            s += 1
    return s


def _check_flow_params(D, dt_max_us, tol, onset_us=0):
    if isinstance(D, bool) or not isinstance(D, int) or D < 1:
        raise ValueError(f"D must be a positive int, got {D!r}")
    if not dt_max_us > 0:
        raise ValueError(f"dt_max_us must be positive, got {dt_max_us!r}")
    if not tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")
    if isinstance(onset_us, bool) or not isinstance(onset_us, int) or onset_us < 0:
        raise ValueError(f"onset_us must be an int >= 0, got {onset_us!r}")


def triplet_samples(sae: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor,
                    p: torch.Tensor | None, b: torch.Tensor | None = None, D: int = 2, dt_max_us: int = 50_000,
                    tol: float = 0.125, onset_us: int = 0,
                    last: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Triplet flow samples of a packet of events against ``sae`` (the SAE before the packet).

    Each event sees ``sae`` updated with the strictly earlier events of the packet (module docstring). With
    ``onset_us > 0`` only crossing onsets are matched, judged by ``last`` (each pixel's newest event time before
    the packet, the shape of ``sae``; required then). Neither tensor is modified.

    Shape:
        sae, last: ``(B, C, H, W)`` int64 us; x, y, t, p, b: ``(N,)``.
        Returns ``event (S,)`` int64 index into the packet (sorted) and ``flow (S, 2)`` float32 px/s.
    """
    _check_flow_params(D, dt_max_us, tol, onset_us)
    _check_sae(sae)
    if onset_us > 0 and (not isinstance(last, torch.Tensor) or last.dtype != torch.int64 or last.shape != sae.shape):
        raise ValueError(f"onset_us > 0 needs last, an int64 tensor of the SAE's shape {tuple(sae.shape)}")
    pad = 2 * D
    sae_pad = _pad_sae(sae, pad)
    last_pad = _pad_sae(last, pad) if onset_us > 0 else sae_pad[:0]
    C = sae_pad.shape[1]
    xn, yn, tn, pn, bn, batched = event_arrays(C, x, y, t, p, b)
    ev, flow, ok = _match_packet(sae_pad.numpy(), last_pad.numpy(), xn, yn, tn, pn, bn, C, batched,
                                 _direction_array(D), pad, dt_max_us, tol, onset_us, max(xn.shape[0], 1))
    if not ok:
        range_error(tuple(sae.shape), x, y, t, p, b)
    return torch.from_numpy(ev), torch.from_numpy(flow)


def block_grid(height: int, width: int, block: int) -> tuple[int, int, torch.Tensor]:
    """Block grid ``(Gy, Gx, centres)``: ``centres (Gy * Gx, 2)`` float32 ``(u, v)`` of each block's in-image area."""
    gy, gx = math.ceil(height / block), math.ceil(width / block)
    u0 = torch.arange(gx) * block
    v0 = torch.arange(gy) * block
    cu = (u0 + (torch.clamp(width - u0, max=block) - 1) / 2.0).float()
    cv = (v0 + (torch.clamp(height - v0, max=block) - 1) / 2.0).float()
    return gy, gx, torch.stack(torch.meshgrid(cu, cv, indexing="xy"), -1).reshape(-1, 2)


def register_blocks(block_id: torch.Tensor, event: torch.Tensor, flow: torch.Tensor, pixel: torch.Tensor,
                    n_blocks: int, min_samples: int = 20, max_candidates: int = 128, tie_tol: float = 0.02,
                    estimate: str = "normal", inlier: float = 0.25):
    """Per-block robust flow: ``argmin_{F in M} sum_i min_{F_ic in M_i} |F - F_ic|`` (module docstring).

    Args:
        block_id: ``(S,)`` int64 block of each sample, in ``[0, n_blocks)``.
        event: ``(S,)`` int64 event id of each sample (samples of one event share it and its block).
        flow: ``(S, 2)`` float candidate flows, px/s.
        pixel: ``(S, 2)`` float ``(u, v)`` pixel of each sample's event.
        n_blocks: number of blocks (all batch elements together).
        min_samples: samples a block needs to be valid.
        max_candidates: cap on the samples evaluated per block.
        tie_tol: relative tie tolerance (0 = exact ties only).
        estimate: ``"register"``: the registered candidate itself (the paper); ``"normal"``: the normal
            flow fitted to the inlier events of the registration (module docstring).
        inlier: relative radius defining the inlier events of the registration.

    Returns:
        ``flow (n_blocks, 2)`` float32 px/s (0 where invalid); ``uv (n_blocks, 2)`` float32 mean pixel of
        the inlier samples (NaN where invalid); ``valid (n_blocks,)`` bool; ``count (n_blocks,)`` int64.
    """
    if min_samples < 1 or max_candidates < 1 or tie_tol < 0 or inlier <= 0:
        raise ValueError("min_samples and max_candidates must be >= 1, tie_tol >= 0 and inlier > 0, got "
                         f"{min_samples}, {max_candidates}, {tie_tol}, {inlier}")
    if estimate not in ("register", "normal"):
        raise ValueError(f"estimate must be 'register' or 'normal', got {estimate!r}")
    out, uv, valid, count = _register(_ints(block_id), _ints(event), flow.numpy(), pixel.numpy(), n_blocks,
                                      min_samples, max_candidates, tie_tol, estimate, inlier, _NAN_UV)
    return torch.from_numpy(out), torch.from_numpy(uv), torch.from_numpy(valid), torch.from_numpy(count)


_NAN_UV = np.full((1, 2), np.nan, dtype=np.float32)


def _ints(t: torch.Tensor) -> np.ndarray:
    return t.numpy() if t.dtype == torch.int64 else t.long().numpy()


def _register(block_id: np.ndarray, event: np.ndarray, flow: np.ndarray, pixel: np.ndarray, n_blocks: int,
              min_samples: int, max_candidates: int, tie_tol: float, estimate: str, inlier: float, fill: np.ndarray):
    """:func:`register_blocks` on numpy arrays; an invalid block ``k`` gets ``uv = fill[k % len(fill)]``."""
    out = np.zeros((n_blocks, 2), dtype=np.float32)
    uv = np.empty((n_blocks, 2), dtype=np.float32)
    valid = np.empty(n_blocks, dtype=np.bool_)
    count = np.empty(n_blocks, dtype=np.int64)
    if block_id.shape != event.shape or flow.shape != block_id.shape + (2,) or pixel.shape != flow.shape:
        raise ValueError(f"need block_id, event (S,) and flow, pixel (S, 2), got {block_id.shape}, {event.shape}, "
                         f"{flow.shape}, {pixel.shape}")
    if not _register_all(block_id, event, flow, pixel, min_samples, max_candidates, float(tie_tol),
                         estimate == "normal", float(inlier), fill, out, uv, valid, count):
        raise ValueError(f"block_id must lie in [0, {n_blocks})")
    return out, uv, valid, count


@kernel
def _register_all(block_id, event, flow, pixel, min_samples, max_candidates, tie_tol, normal, inlier, fill, out,
                  uv_out, valid, count):
    """:func:`register_blocks` into ``out``, ``uv_out``, ``valid``, ``count`` (``n_blocks`` rows); False (nothing
    registered) if a block id lies outside ``[0, n_blocks)``.

    The samples of the valid blocks are grouped by block in event order (:func:`_group`), then each block's
    are subsampled (:func:`_subsample`) and registered (:func:`_register_block`)."""
    n_blocks = count.shape[0]
    count[:] = 0
    in_order = True
    for i in range(block_id.shape[0]):
        k = block_id[i]
        if k < 0 or k >= n_blocks:
            return False
        count[k] += 1
        in_order &= i == 0 or event[i] >= event[i - 1]
    if not in_order:  # stably by event: the grouping keeps that order
        perm = np.argsort(event, kind="mergesort")
        block_id, event, flow, pixel = block_id[perm], event[perm], flow[perm], pixel[perm]
    cap = np.int64(1)
    for k in range(n_blocks):
        valid[k] = count[k] >= min_samples
        if valid[k]:
            cap = max(cap, min(count[k], max_candidates))
    rec, rec_event = _group(block_id, event, flow, pixel, valid, count)
    F = np.empty((4, cap))
    ev = np.empty(cap, dtype=np.int64)
    work = _scratch(cap)
    pos = 0
    nf = fill.shape[0]
    for k in range(n_blocks):
        if not valid[k]:
            uv_out[k, 0], uv_out[k, 1] = fill[k % nf, 0], fill[k % nf, 1]
            continue
        n = _subsample(rec[pos:pos + count[k]], rec_event[pos:pos + count[k]], max_candidates, F, ev)
        pos += count[k]
        out[k, 0], out[k, 1], uv_out[k, 0], uv_out[k, 1] = _register_block(
            F[0, :n], F[1, :n], ev[:n], F[2, :n], F[3, :n], tie_tol, normal, inlier, work)
    return True


class _Scratch(NamedTuple):
    """Work arrays of :func:`_register_block` for up to ``cap`` samples: ``f64 (5, cap)``, ``f32 (6, cap)``,
    ``idx (3, cap)`` int64 (row 2: ``0 .. cap - 1``), ``exact (cap,)`` bool."""

    f64: np.ndarray
    f32: np.ndarray
    idx: np.ndarray
    exact: np.ndarray


@kernel
def _scratch(cap):
    idx = np.empty((3, cap), dtype=np.int64)
    idx[2] = np.arange(cap)
    return _Scratch(np.empty((5, cap)), np.empty((6, cap), dtype=np.float32), idx, np.empty(cap, dtype=np.bool_))


@kernel
def _group(block_id, event, flow, pixel, valid, count):
    """The samples (in event order) of the valid blocks grouped by block, in order, as rows ``(F_u, F_v, pixel_u,
    pixel_v)`` and their events: a counting sort by block, stable.

    Shape: block_id, event ``(S,)``; flow, pixel ``(S, 2)``; valid, count ``(n_blocks,)``. Returns ``rec (n, 4)``
    float64 and ``event (n,)``, ``n = sum(count[valid])``."""
    pos = np.empty(count.shape[0], dtype=np.int64)
    n = 0
    for k in range(count.shape[0]):
        pos[k] = n
        if valid[k]:
            n += count[k]
    rec = np.empty((n, 4))
    rec_event = np.empty(n, dtype=np.int64)
    for i in range(block_id.shape[0]):
        k = block_id[i]
        if valid[k]:
            d = pos[k]
            pos[k] += 1
            rec[d, 0], rec[d, 1] = flow[i, 0], flow[i, 1]
            rec[d, 2], rec[d, 3] = pixel[i, 0], pixel[i, 1]
            rec_event[d] = event[i]
    return rec, rec_event


@kernel
def _subsample(rec, event, max_candidates, F, ev):
    """The samples a block registers: of its samples ``rec`` (rows of :func:`_group`, of ``event``, in event
    order) those of every ``s``-th event, ``s = ceil(len(rec) / max_candidates)``, the first ``max_candidates`` of
    them. Writes their ``(F_u, F_v, pixel_u, pixel_v)`` to ``F[:, :n]`` and their event rank (``0 .. E - 1``) to
    ``ev[:n]``; returns ``n``."""
    stride = (rec.shape[0] + max_candidates - 1) // max_candidates
    phase = rank = n = 0  # the event rank within the block is rank * stride + phase
    for q in range(rec.shape[0]):
        if q > 0 and event[q] != event[q - 1]:
            phase += 1
            if phase == stride:
                phase, rank = 0, rank + 1
        if phase == 0:
            if n == max_candidates:
                break
            for r in range(4):
                F[r, n] = rec[q, r]
            ev[n] = rank
            n += 1
    return n


@kernel
def _register_block(F0, F1, ev, px, py, tie_tol, normal, inlier, work):
    """Registration of one block's ``K`` samples ``(F0, F1)`` of events ``ev`` (sorted ranks ``0 .. E - 1``) at
    pixels ``(px, py)`` (module docstring). Returns ``(flow_u, flow_v, u, v)``.

    The costs ``C(F_c)``, then the spreads of the near-optimal candidates, are bounded in float32
    (:func:`_sum_bounds`) and evaluated exactly, as sums of float64 distances, only where the bounds leave
    the comparisons that pick the block's candidate open (:func:`_least`): the choice is that of evaluating
    them all.

    Shape: F0, F1, ev, px, py ``(K,)``; work: :class:`_Scratch` of at least ``K``."""
    K = F0.shape[0]
    E = ev[K - 1] + 1
    cand, lo, hi, exact = work.idx[2, :K], work.f64[0, :K], work.f64[1, :K], work.exact[:K]
    _sum_bounds(F0, F1, ev, cand, lo, hi, exact, work)
    c_min = _least(F0, F1, ev, cand, lo, hi, exact, work, np.bool_(True))[1]
    # Among the near-optimal candidates, C <= C_min + tie_tol E |F|, the one closest to all samples.
    thr, norm, undecided, near = work.f64[2, :K], work.f64[4, :K], work.idx[0], work.idx[1]
    for c in range(K):
        norm[c] = np.sqrt(F0[c] ** 2 + F1[c] ** 2)
        thr[c] = c_min + tie_tol * E * norm[c]
    n = 0
    for c in range(K):
        undecided[n] = c
        n += not (exact[c] | (hi[c] <= thr[c]) | (lo[c] > thr[c]))
    _exact_sums(F0, F1, ev, cand, undecided[:n], lo, hi, exact, work)
    n = 0
    for c in range(K):
        near[n] = c
        n += hi[c] <= thr[c]
    near, lo, hi, exact = near[:n], lo[:n], hi[:n], exact[:n]
    _sum_bounds(F0, F1, cand, near, lo, hi, exact, work)  # ranks cand = 0 .. K - 1: the spreads sum_j |F - F_j|
    q = _least(F0, F1, cand, near, lo, hi, exact, work, np.bool_(False))[0]
    return _inlier_fit(F0, F1, ev, px, py, norm, near[q] if q >= 0 else 0, normal, inlier, work)


@kernel
def _dist_sums(C0, C1, F0, F1, ev, row, out):
    """``out[q] = sum_e min_{j in e} |C_q - F_j|`` over the events ``e`` of the samples ``F_j`` in order, in the
    arrays' float type; the minimum is taken of the squared norms, then its root (the same value: the root is
    monotonic).

    Shape: C0, C1, row (scratch), out ``(Q,)``; F0, F1, ev ``(K,)`` (ev: event ranks, grouped)."""
    K = F0.shape[0]
    out[:] = 0
    j = 0
    while j < K:
        e = ev[j]
        f0, f1 = F0[j], F1[j]
        for q in range(C0.shape[0]):
            a, b = C0[q] - f0, C1[q] - f1
            row[q] = a * a + b * b
        j += 1
        while j < K and ev[j] == e:
            f0, f1 = F0[j], F1[j]
            for q in range(C0.shape[0]):
                a, b = C0[q] - f0, C1[q] - f1
                row[q] = min(row[q], a * a + b * b)
            j += 1
        for q in range(C0.shape[0]):
            out[q] += np.sqrt(row[q])


@kernel(fastmath={"reassoc", "nsz"})
def _spread_sums(C0, C1, F0, F1, out):
    """``out[q] = sum_j |C_q - F_j|``: :func:`_dist_sums` of samples that are each an event of their own, one
    candidate at a time with the sum in any order (vector lanes), which is as exact as the order of
    :func:`_dist_sums` for the bounds of :func:`_sum_bounds` (the rounding of a sum of positive terms is bounded
    alike in every order).

    Shape: C0, C1, out ``(Q,)``; F0, F1 ``(K,)``; float32."""
    for q in range(C0.shape[0]):
        c0, c1 = C0[q], C1[q]
        acc = np.float32(0.0)
        for j in range(F0.shape[0]):
            a, b = c0 - F0[j], c1 - F1[j]
            acc += np.sqrt(a * a + b * b)
        out[q] = acc


@kernel
def _sum_bounds(F0, F1, ev, cand, lo, hi, exact, work):
    """``lo[q] <= S_q <= hi[q]`` for the float64 sums ``S_q`` of :func:`_dist_sums` of the candidates
    ``C_q = F_cand[q]`` from their float32 evaluation ``s``: ``s +- 2^-21 E (s + 2 M) + 2^-60 E``, which bounds the
    float32 rounding of the differences, squares, roots and the sum of ``E`` terms, of the inputs (``M``: the
    largest ``|F|`` component; 0 if all are float32 numbers, as the matching writes them) and of underflow,
    with room. Where float32 would not do (huge or non-finite flows, ``E > 4096``) the sums themselves
    (``exact[q]``).

    Shape: F0, F1, ev ``(K,)``; cand, lo, hi, exact ``(Q,)``."""
    K, Q = F0.shape[0], cand.shape[0]
    E = ev[K - 1] + 1
    G0, G1, C0, C1, s = work.f32[0, :K], work.f32[1, :K], work.f32[2, :Q], work.f32[3, :Q], work.f32[5, :Q]
    M, fits, rounded = 0.0, E <= 4096, False
    for j in range(K):
        m = max(abs(F0[j]), abs(F1[j]))
        fits &= m <= 2.0 ** 60
        M = max(M, m)
        G0[j], G1[j] = F0[j], F1[j]
        rounded |= (G0[j] != F0[j]) | (G1[j] != F1[j])
    exact[:] = False
    if not fits:
        _exact_sums(F0, F1, ev, cand, work.idx[2, :Q], lo, hi, exact, work)
        return
    for q in range(Q):
        C0[q], C1[q] = G0[cand[q]], G1[cand[q]]
    if E == K:  # one sample per event (the spreads): no minima
        _spread_sums(C0, C1, G0, G1, s)
    else:
        _dist_sums(C0, C1, G0, G1, ev, work.f32[4, :Q], s)
    M = 2.0 * M if rounded else 0.0
    for q in range(Q):
        err = 2.0 ** -21 * E * (s[q] + M) + 2.0 ** -60 * E
        lo[q], hi[q] = s[q] - err, s[q] + err


@kernel
def _exact_sums(F0, F1, ev, cand, sel, lo, hi, exact, work):
    """``lo[q] = hi[q] =`` the float64 sum of :func:`_dist_sums` of candidate ``F_cand[q]``, ``exact[q] = True``,
    for ``q`` in ``sel`` (unless already exact), one candidate at a time (:func:`_dist_sum`)."""
    row = work.f64[3, :F0.shape[0]]
    for q in sel:
        if not exact[q]:
            lo[q] = hi[q] = _dist_sum(F0[cand[q]], F1[cand[q]], F0, F1, ev, row)
            exact[q] = True


@kernel
def _dist_sum(c0, c1, F0, F1, ev, row):
    """:func:`_dist_sums` of one candidate ``(c0, c1)``, the same value: the squared distances, the per-event
    minima (in place: event ``e`` is no later than its samples) and their roots in vector loops, then the sum
    in order.

    Shape: F0, F1, ev, row (scratch) ``(K,)``."""
    K = F0.shape[0]
    for j in range(K):
        a, b = c0 - F0[j], c1 - F1[j]
        row[j] = a * a + b * b
    m = np.inf
    for j in range(K):
        m = min(np.inf if j == 0 or ev[j] != ev[j - 1] else m, row[j])
        row[ev[j]] = m
    E = ev[K - 1] + 1
    for e in range(E):
        row[e] = np.sqrt(row[e])
    s = 0.0
    for e in range(E):
        s += row[e]
    return s


@kernel
def _least(F0, F1, ev, cand, lo, hi, exact, work, value):
    """The first ``q`` with the least sum ``S_q`` and that sum (``(-1, inf)`` if there are no candidates), from the
    bounds of :func:`_sum_bounds`: only the candidates whose lower bound does not exceed the least upper bound
    can be it; they are evaluated exactly (:func:`_exact_sums`), unless there is one, certainly finite, and its
    sum is not asked for (``value`` False: the sum returned is then ``inf``)."""
    top = np.inf
    for q in range(cand.shape[0]):
        if hi[q] < top:
            top = hi[q]
    sel = work.idx[0]
    n = 0
    for q in range(cand.shape[0]):
        sel[n] = q
        n += not (lo[q] > top)
    if n == 1 and not value and hi[sel[0]] < np.inf:
        return sel[0], np.inf
    _exact_sums(F0, F1, ev, cand, sel[:n], lo, hi, exact, work)
    best, least = -1, np.inf
    for q in sel[:n]:
        if hi[q] < least:
            best, least = q, hi[q]
    return best, least


@kernel
def _inlier_fit(F0, F1, ev, px, py, norm, best, normal, inlier, work):
    """Flow and ``uv`` of a block registered to candidate ``best``: over the samples of its inlier events (nearest
    sample within ``inlier |F_best|`` of ``F_best``) the mean pixel and, if ``normal``, the normal flow fitted to
    them (:func:`_normal_flow`), else ``F_best``. Shape: all ``(K,)`` (``norm``: ``|F_j|``); returns four
    floats."""
    K = F0.shape[0]
    fx, fy = F0[best], F1[best]
    radius = inlier * norm[best]
    d2, w, least = work.f64[2, :K], work.f64[3, :K], work.f64[0, :K]
    for j in range(K):
        a, b = fx - F0[j], fy - F1[j]
        d2[j] = a * a + b * b
        w[j] = 1.0 / max(norm[j], 1e-12)
    m = np.inf
    for j in range(K):  # least[e]: the least d2 over event e's samples
        m = min(np.inf if j == 0 or ev[j] != ev[j - 1] else m, d2[j])
        least[ev[j]] = m
    for e in range(ev[K - 1] + 1):  # 1.0: an inlier event
        least[e] = np.sqrt(least[e]) <= radius
    a00 = a01 = a11 = r0 = r1 = su = sv = sw = 0.0
    for j in range(K):  # adding 0.0 leaves a sum as it is (none is -0.0)
        ok = least[ev[j]] != 0.0
        su += px[j] if ok else 0.0
        sv += py[j] if ok else 0.0
        sw += 1.0 if ok else 0.0
        if normal:
            a00 += w[j] * F0[j] * F0[j] if ok else 0.0
            a01 += w[j] * F0[j] * F1[j] if ok else 0.0
            a11 += w[j] * F1[j] * F1[j] if ok else 0.0
            r0 += w[j] * F0[j] if ok else 0.0
            r1 += w[j] * F1[j] if ok else 0.0
    if normal:
        fx, fy = _normal_flow(a00, a01, a11, r0, r1)
    return fx, fy, su / sw, sv / sw


@kernel
def _normal_flow(a00, a01, a11, r0, r1):
    """Normal flow ``g / |g|^2`` of the min-norm least-squares gradient ``g = pinv(A) r``, ``A`` symmetric 2 x 2
    (each inlier sample ``F_j`` is the line ``F_j . g = 1``, weighted ``1 / |F_j|``). Eigenvalues below
    ``2 eps`` of the largest are treated as zero (a single sample direction)."""
    half_tr, det = 0.5 * (a00 + a11), a00 * a11 - a01 * a01
    disc = np.sqrt(max(half_tr * half_tr - det, 0.0))
    l1, l2 = half_tr + disc, half_tr - disc  # l1 >= l2 >= 0
    # unit eigenvector of l1
    if abs(a01) > 0.0:
        e0, e1 = l1 - a11, a01
    elif a00 >= a11:
        e0, e1 = 1.0, 0.0
    else:
        e0, e1 = 0.0, 1.0
    n = np.sqrt(e0 * e0 + e1 * e1)
    e0, e1 = e0 / n, e1 / n
    cut = 2.0 * np.finfo(np.float64).eps * l1
    gx = gy = 0.0
    if l1 > cut:
        p = (e0 * r0 + e1 * r1) / l1
        gx, gy = gx + p * e0, gy + p * e1
    if l2 > cut:
        p = (-e1 * r0 + e0 * r1) / l2
        gx, gy = gx - p * e1, gy + p * e0
    n2 = max(gx * gx + gy * gy, 1e-30)
    return gx / n2, gy / n2


@kernel
def _sample_blocks(ev, x, y, b, batched, block_x, block_y, G):
    """Block ``b G + block_y[y] + block_x[x]`` and pixel ``(x, y)`` of the event of each sample.

    Shape: ev ``(S,)``; x, y, b ``(N,)``; block_x ``(W,)``, block_y ``(H,)``; returns ``(S,)`` and ``(S, 2)``."""
    S = ev.shape[0]
    gid = np.empty(S, dtype=np.int64)
    pixel = np.empty((S, 2), dtype=np.int64)
    for s in range(S):
        i = ev[s]
        gid[s] = (b[i] if batched else 0) * G + block_y[y[i]] + block_x[x[i]]
        pixel[s, 0], pixel[s, 1] = x[i], y[i]
    return gid, pixel


@kernel
def flow_packet(sae, last, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, onset_us, chunk, block_x, block_y, G,
                min_samples, max_candidates, tie_tol, normal, inlier, fill, out, uv, valid, count):
    """:meth:`TripletFlow.forward` in one compiled call, unchecked, for compiled callers.

    The events of :func:`event_arrays` are matched against the padded SAE ``sae`` ``(B, C, H + 2 pad, W + 2 pad)``
    int64 (``TripletFlow.sae_padded``, written in place, as ``last``, ``TripletFlow.last_padded``) with the flow's
    constants (``*TripletFlow.params``, see :class:`FlowParams`), and the blocks registered into ``out`` (zeros on
    entry) and ``uv`` ``(B, G, 2)`` float32 and ``valid`` bool, ``count`` int64 ``(B, G)``. Returns False, nothing
    written, if an event lies outside the SAE. (Its steps: :func:`_match_packet`, :func:`_sample_blocks`,
    :func:`_register_all`.)"""
    event, flow, ok = _match_packet(sae, last, x, y, t, p, b, C, batched, dirs, pad, dt_max_us, tol, onset_us, chunk)
    if ok:
        B = count.shape[0]
        block_id, pixel = _sample_blocks(event, x, y, b, batched, block_x, block_y, G)
        _register_all(block_id, event, flow, pixel, min_samples, max_candidates, tie_tol, normal, inlier, fill,
                      out.reshape(B * G, 2), uv.reshape(B * G, 2), valid.reshape(B * G), count.reshape(B * G))
    return ok


class FlowParams(NamedTuple):
    """The constants :func:`flow_packet` takes after the events, in its argument order (``TripletFlow.params``).

    ``dirs`` ``(K, 2)`` triplet directions, ``pad`` the SAE border (``2 D``), ``dt_max_us``, ``tol``, ``onset_us``,
    ``chunk`` (see :class:`TripletFlow`), ``block_x`` ``(W,)`` block column of each pixel column, ``block_y``
    ``(H,)`` first block index of each pixel row, ``n_blocks`` ``G``, ``min_samples``, ``max_candidates``,
    ``tie_tol``, ``normal`` (``estimate == "normal"``), ``inlier``, ``centres`` ``(G, 2)`` block centres in pixels.
    """
    dirs: np.ndarray
    pad: int
    dt_max_us: int
    tol: float
    onset_us: int
    chunk: int
    block_x: np.ndarray
    block_y: np.ndarray
    n_blocks: int
    min_samples: int
    max_candidates: int
    tie_tol: float
    normal: bool
    inlier: float
    centres: np.ndarray


class TripletFlow(nn.Module):
    """Stateful triplet-matching flow for ``B`` event streams, one flow field per packet.

    Args:
        height, width: sensor size in pixels.
        batch_size: number of independent streams ``B``.
        block: RoI size in pixels (20..40 typical).
        min_samples: samples a block needs for a flow vector.
        D: triplet radius (offsets ``|dx|, |dy| <= D``).
        dt_max_us: maximum ``t0 - t1``, microseconds.
        tol: triplet timing tolerance ``|1 - dt12 / dt01| < tol``.
        onset_us: only an event whose pixel was silent longer than this is matched (a crossing's onset, module
            docstring); 0 matches every event.
        per_polarity: one SAE channel per polarity (triplets match events of equal polarity only).
        max_candidates, tie_tol, estimate, inlier: see :func:`register_blocks`.
        chunk: a packet of more events is matched this many at a time, in bounded memory and with the
            same result exactly (module docstring).

    Buffers:
        sae: ``(B, C, H, W)`` int64 time in us of the last event matched (the newest crossing onset with
            ``onset_us > 0``; :data:`NEVER` if none), ``C = 2`` if ``per_polarity`` else 1.
        last_padded: with ``onset_us > 0``, each pixel's newest event time, padded as ``sae_padded`` (else empty).

    ``forward(x, y, t, p, b=None) -> FlowField`` uses only the packet's triplets (matched against the SAE
    history) and then leaves the SAE updated with the packet. With ``rows=slice`` the packet holds the events of
    the batch elements ``rows`` only (``b`` counted from ``rows.start``) and the flow field is theirs: threads may
    update disjoint rows at once.
    """

    sae: torch.Tensor

    @classmethod
    def from_config(cls, height: int, width: int, cfg: FlowConfig, batch_size: int = 1) -> "TripletFlow":
        """The flow of the config section ``flow`` (:class:`~torchevtrack.config.FlowConfig`) for ``B`` streams."""
        return cls(height, width, batch_size=batch_size, block=cfg.block, min_samples=cfg.min_samples, D=cfg.radius,
                   dt_max_us=cfg.dt_max_us, tol=cfg.tol, onset_us=cfg.onset_us, estimate=cfg.estimate)

    def __init__(self, height: int, width: int, batch_size: int = 1, block: int = FlowConfig.block,
                 min_samples: int = FlowConfig.min_samples, D: int = FlowConfig.radius,
                 dt_max_us: int = FlowConfig.dt_max_us, tol: float = FlowConfig.tol,
                 onset_us: int = FlowConfig.onset_us, per_polarity: bool = False,
                 max_candidates: int = 128, tie_tol: float = 0.02,
                 estimate: str = FlowConfig.estimate, inlier: float = 0.25, chunk: int = 2 ** 16):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size), ("block", block),
                        ("min_samples", min_samples), ("max_candidates", max_candidates), ("chunk", chunk)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        _check_flow_params(D, dt_max_us, tol, onset_us)
        if tie_tol < 0 or inlier <= 0 or estimate not in ("register", "normal"):
            raise ValueError("need tie_tol >= 0, inlier > 0 and estimate in {'register', 'normal'}, got "
                             f"{tie_tol!r}, {inlier!r}, {estimate!r}")
        self.height, self.width, self.block = height, width, block
        self.min_samples, self.D, self.dt_max_us, self.tol = min_samples, D, int(dt_max_us), float(tol)
        self.onset_us = onset_us
        self.per_polarity = bool(per_polarity)
        self.max_candidates, self.tie_tol = max_candidates, float(tie_tol)
        self.estimate, self.inlier = estimate, float(inlier)
        self.chunk = chunk
        self.pad = 2 * D
        C = 2 if per_polarity else 1
        self.gy, self.gx, centres = block_grid(height, width, block)
        self.register_buffer("centres", centres, persistent=False)
        self.params = FlowParams(_direction_array(D), self.pad, self.dt_max_us, self.tol, onset_us, chunk,
                                 np.arange(width) // block, np.arange(height) // block * self.gx, self.gy * self.gx,
                                 min_samples, max_candidates, self.tie_tol, estimate == "normal", self.inlier,
                                 centres.numpy())
        # Stored padded by 2D with NEVER so that p1, p2 lookups need no bounds checks.
        shape = (batch_size, C, height + 2 * self.pad, width + 2 * self.pad)
        self.register_buffer("sae_padded", torch.full(shape, NEVER, dtype=torch.int64))
        self.register_buffer("last_padded", torch.full(shape if onset_us > 0 else (batch_size, C, 0, 0), NEVER,
                                                       dtype=torch.int64))

    @property
    def sae(self) -> torch.Tensor:
        """``(B, C, H, W)`` view of the SAE."""
        p = self.pad
        return self.sae_padded[:, :, p:p + self.height, p:p + self.width]

    @property
    def newest(self) -> torch.Tensor:
        """``(B, C, H, W)`` view of each pixel's newest event time in us, every event counted (``last_padded`` with
        ``onset_us > 0``, else the SAE itself)."""
        if self.onset_us == 0:
            return self.sae
        p = self.pad
        return self.last_padded[:, :, p:p + self.height, p:p + self.width]

    @property
    def n_blocks(self) -> int:
        return self.gy * self.gx

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget every element's events, or those of the elements selected by ``mask`` (``(B,)`` bool or
        ``(K,)`` indices, see :func:`~torchevtrack.stages.batch_mask`); the others are untouched."""
        for buf in (self.sae_padded, self.last_padded):
            if mask is None:
                buf.fill_(NEVER)
            else:
                buf.masked_fill_(batch_mask(mask, buf.shape[0])[:, None, None, None], NEVER)

    def forward(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None = None,
                b: torch.Tensor | None = None, rows: slice | None = None) -> FlowField:
        sae = self.sae_padded if rows is None else self.sae_padded[rows]
        last = self.last_padded if rows is None else self.last_padded[rows]
        B, C = sae.shape[:2]
        G = self.gy * self.gx
        xn, yn, tn, pn, bn, batched = event_arrays(C, x, y, t, p, b)
        out = np.zeros((B, G, 2), dtype=np.float32)
        uv = np.empty((B, G, 2), dtype=np.float32)
        valid = np.empty((B, G), dtype=np.bool_)
        count = np.empty((B, G), dtype=np.int64)
        if not flow_packet(sae.numpy(), last.numpy(), xn, yn, tn, pn, bn, C, batched, *self.params, out, uv, valid,
                           count):
            range_error((B, C, self.height, self.width), x, y, t, p, b)
        return FlowField(torch.from_numpy(uv), torch.from_numpy(out), torch.from_numpy(valid), torch.from_numpy(count))

    def _match(self, xi: torch.Tensor, yi: torch.Tensor, ch: torch.Tensor, t: torch.Tensor):
        """Triplet samples of prepared events (:func:`_prepare`: pixel ``xi, yi``, SAE plane ``ch = b C + p``),
        at most ``chunk`` events at a time, updating the SAE as they go.

        Shape: prepared events ``(N,)``; returns ``event (S,)`` (index into the packet) and ``flow (S, 2)``.
        """
        ev, flow, _ = _match_packet(self.sae_padded.numpy(), self.last_padded.numpy(), xi.numpy(), yi.numpy(),
                                    t.numpy(), _NONE, ch.numpy(), 1, True, *self.params[:6])
        return torch.from_numpy(ev), torch.from_numpy(flow)

    def extra_repr(self) -> str:
        return (f"height={self.height}, width={self.width}, block={self.block}, min_samples={self.min_samples}, "
                f"D={self.D}, dt_max_us={self.dt_max_us}, tol={self.tol}, onset_us={self.onset_us}, "
                f"per_polarity={self.per_polarity}, estimate={self.estimate!r}")
