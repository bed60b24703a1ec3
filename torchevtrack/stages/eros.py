"""Stage 1: EROS, the exponentially reduced ordinal surface (velocity-independent event image), and the timestamp
surface of the newest event per pixel (:class:`TimeSurface`), which weighs the EROS by recency when it is observed
(:class:`Recency`: one window per element, fixed or following the image speed).

Definition, per event at pixel ``(x, y)`` of batch element ``b``, in order: every pixel of the
``k x k`` window centred on ``(x, y)`` (clipped to the image, the event pixel included) is multiplied
by ``lam = decay ** (1 / k)``, then ``S[b, y, x] = 1``.

The update is that definition itself, run event by event in a compiled kernel (numba): each event
costs ``k * k`` multiplies, so a packet costs ``O(N k^2)`` time and no memory beyond the surface, and
the result is order preserving by construction. The surface is float32 and each multiply rounds to
float32, so it stays within ~1e-6 of a float64 evaluation of the same definition.

Events are packed as 1-D tensors ``x``, ``y`` (pixel column / row) and ``b`` (batch index, or ``None``
for all-zero); within each batch element the packed order is time order.

Example:
    >>> import torch
    >>> from torchevtrack.stages.eros import EROS
    >>> eros = EROS(4, 5, kernel_size=3, decay=0.5)
    >>> s = eros(torch.tensor([1, 2]), torch.tensor([1, 1]))
    >>> round(float(s[0, 1, 1]), 4), float(s[0, 1, 2])  # lam = 0.5 ** (1/3)
    (0.7937, 1.0)
"""

from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from torchevtrack.config import RECENCY_STEP_US, ErosConfig, recency_windows
from torchevtrack.kernels import kernel
from torchevtrack.prefetch import AHEAD, prefetch
from torchevtrack.stages import NEVER, batch_mask, canvas_taps

__all__ = ["EROS", "Recency", "RecencyArrays", "TimeSurface", "bind_observe", "canvas_kernel",
           "canvas_observation", "check_fields", "check_times", "decay_tables", "eros_kernel", "eros_update",
           "eros_update_", "events_inside", "follow_speed", "observation", "prepare_events", "recency_arrays",
           "recent_observation", "time_kernel", "time_surface_update_"]


def prepare_events(x: torch.Tensor, y: torch.Tensor, b: torch.Tensor | None, height: int, width: int,
                   batch_size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Check packed event coordinates and return them as int64 ``(x, y, b)``.

    Shape:
        x, y, b: ``(N,)`` integer tensors; ``b`` may be ``None`` (all events in batch element 0).
        Returns three ``(N,)`` int64 tensors.

    Raises:
        TypeError: a field is not an integer tensor.
        ValueError: shapes differ, or a coordinate is outside ``[0, width) x [0, height)`` or a
            batch index outside ``[0, batch_size)``.
    """
    check_fields(x, y, b)
    xi, yi = x.long(), y.long()
    bi = torch.zeros_like(xi) if b is None else b.long()
    if xi.numel():
        for name, v, hi in (("x", xi, width), ("y", yi, height), ("b", bi, batch_size)):
            lo_v, hi_v = torch.aminmax(v)
            if int(lo_v) < 0 or int(hi_v) >= hi:
                raise ValueError(f"{name} must lie in [0, {hi}), got values in [{int(lo_v)}, {int(hi_v)}]")
    return xi, yi, bi


def check_fields(x, y, b) -> None:
    """Check the types and shapes of packed event coordinates, as every stage that takes events does: ``x, y`` and
    ``b`` (``None``: not checked) 1-D integer CPU tensors of one shape. Raises the TypeError or ValueError of
    :func:`prepare_events`; the ranges are not checked (:func:`prepare_events`, :func:`events_inside`)."""
    fields = {"x": x, "y": y} if b is None else {"x": x, "y": y, "b": b}
    for name, f in fields.items():
        if not isinstance(f, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(f).__name__}")
        if f.is_floating_point() or f.is_complex() or f.dtype == torch.bool:
            raise TypeError(f"{name} must be an integer tensor, got {f.dtype}")
        if f.ndim != 1 or f.shape != x.shape:
            raise ValueError(f"{name} must be 1-D with the shape of x {tuple(x.shape)}, got {tuple(f.shape)}")
        if f.device.type != "cpu":
            raise ValueError(f"{name} must be a CPU tensor, got one on {f.device}")


def check_times(t, shape) -> None:
    """Check that ``t`` is an int64 tensor of microseconds, one per event (``shape``, that of ``x``); a TypeError
    otherwise, as every stage that takes event times raises it."""
    if not isinstance(t, torch.Tensor) or t.dtype != torch.int64 or t.shape != shape:
        raise TypeError(f"t must be an int64 tensor of microseconds with the shape of x {tuple(shape)}")


def _check_params(kernel_size: int, decay: float) -> None:
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size <= 0 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd int, got {kernel_size!r}")
    if not 0.0 < float(decay) < 1.0:
        raise ValueError(f"decay must be in (0, 1), got {decay!r}")


def _check_surface(surface: torch.Tensor) -> None:
    if not isinstance(surface, torch.Tensor) or surface.ndim != 3 or not surface.is_floating_point() \
            or not surface.is_contiguous():
        raise ValueError("surface must be a contiguous floating (B, H, W) tensor, got "
                         f"{getattr(surface, 'dtype', type(surface).__name__)} {tuple(getattr(surface, 'shape', ()))}")


def eros_update_(surface: torch.Tensor, x: torch.Tensor, y: torch.Tensor, b: torch.Tensor | None,
                 kernel_size: int = 7, decay: float = 0.3) -> torch.Tensor:
    """In-place :func:`eros_update`: apply the events to ``surface`` and return it."""
    _check_surface(surface)
    _check_params(kernel_size, decay)
    B, H, W = surface.shape
    check_fields(x, y, b)
    if x.numel():
        lam = surface.numpy().dtype.type(decay ** (1.0 / kernel_size))
        bn = np.zeros(1, dtype=np.int64) if b is None else b.numpy()
        if not eros_kernel(surface.numpy(), x.numpy(), y.numpy(), bn, b is not None, kernel_size // 2, lam):
            prepare_events(x, y, b, H, W, B)  # raises the range error (the kernel checks before it writes)
    return surface


@kernel
def events_inside(x, y, b, batched, B, H, W):
    """Every event of numpy arrays ``x, y`` ``(N,)`` inside ``[0, W) x [0, H)`` with its batch index ``b[i]`` (only
    read when ``batched``) in ``[0, B)``: the range check of :func:`prepare_events`, compiled, for compiled callers
    that check before they write."""
    for i in range(x.shape[0]):
        k = b[i] if batched else 0
        if x[i] < 0 or x[i] >= W or y[i] < 0 or y[i] >= H or k < 0 or k >= B:
            return False
    return True


@kernel
def eros_kernel(surface, x, y, b, batched, r, lam):
    """:func:`eros_update_` on numpy arrays, unchecked, for compiled callers: the events ``x, y`` ``(N,)`` of the
    elements ``b`` ``(N,)`` (read only when ``batched``; else all in element 0) into ``surface`` ``(B, H, W)``, in
    order, with the window radius ``r = kernel_size // 2`` and the factor ``lam`` (:attr:`EROS.lam`, of the surface's
    dtype). Returns False, the surface untouched, if an event lies outside it.

    The window of event ``i + AHEAD`` is prefetched while event ``i`` is written (:mod:`torchevtrack.prefetch`): a
    noise event's window lies out of every cache."""
    B, H, W = surface.shape
    if not events_inside(x, y, b, batched, B, H, W):
        return False
    flat = surface.reshape(B * H * W)
    n = x.shape[0]
    for i in range(n):
        j = i + AHEAD
        if j < n:
            corner = ((b[j] if batched else 0) * H + y[j] - r) * W + x[j] - r
            for dy in range(2 * r + 1):
                prefetch(flat, corner + dy * W)
                prefetch(flat, corner + dy * W + 2 * r)
        u, v, k = x[i], y[i], b[i] if batched else 0
        u0, u1 = max(u - r, 0), min(u + r + 1, W)
        for yy in range(max(v - r, 0), min(v + r + 1, H)):
            row = surface[k, yy]
            if u1 - u0 == 7:  # the default 7 x 7 window away from the border: a fixed-length row (unrolled)
                for dx in range(7):
                    row[u0 + dx] *= lam
            else:
                for xx in range(u0, u1):
                    row[xx] *= lam
        surface[k, v, u] = 1.0
    return True


def eros_update(surface: torch.Tensor, x: torch.Tensor, y: torch.Tensor, b: torch.Tensor | None,
                kernel_size: int = 7, decay: float = 0.3) -> torch.Tensor:
    """Apply a packet of events, in order, to an EROS surface (exact; see the module docstring).

    Args:
        surface: ``(B, H, W)`` float surface, values in ``[0, 1]``.
        x, y: ``(N,)`` integer pixel column / row of each event.
        b: ``(N,)`` integer batch index, or ``None`` (all events in batch element 0).
        kernel_size: odd window size ``k``.
        decay: ``d`` in ``(0, 1)``; every event multiplies its window by ``d ** (1 / k)``.

    Returns:
        A new ``(B, H, W)`` surface; the input is not modified.
    """
    return eros_update_(surface.clone(memory_format=torch.contiguous_format), x, y, b, kernel_size, decay)


def observation(surface: torch.Tensor) -> torch.Tensor:
    """Matching observation of an EROS surface: its 3x3 median blur (mirror border, edge not repeated;
    a one-pixel-wide side, which has nothing to mirror, repeats its edge).

    Shape:
        surface: ``(B, H, W)`` in ``[0, 1]``; returns ``(B, H, W)`` in ``[0, 1]``.
    """
    if not isinstance(surface, torch.Tensor) or surface.ndim != 3:
        raise ValueError(f"surface must be a (B, H, W) tensor, got {tuple(getattr(surface, 'shape', ()))}")
    border = "reflect" if min(surface.shape[-2:]) > 1 else "replicate"
    if not surface.is_floating_point() or not bool(torch.isfinite(surface).all()):
        return kornia.filters.median_blur(surface[:, None], (3, 3), border_type=border)[:, 0]
    return _median3x3(surface, border)


def _median3x3(surface: torch.Tensor, border: str) -> torch.Tensor:
    """3x3 median of finite images: sort the three rows of every column of the padded image, then the median is
    the median of (largest low, median of the middles, smallest high) over three adjacent columns. It selects
    one of the nine values, so it equals any other exact median (e.g. kornia's sorting network) exactly."""
    p = F.pad(surface[:, None], (1, 1, 1, 1), mode=border)[:, 0]
    a, b, c = p[:, :-2], p[:, 1:-1], p[:, 2:]
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    lo, c = torch.minimum(lo, c), torch.maximum(lo, c)
    mid, hi = torch.minimum(hi, c), torch.maximum(hi, c)
    lo = torch.maximum(torch.maximum(lo[..., :-2], lo[..., 1:-1]), lo[..., 2:])
    hi = torch.minimum(torch.minimum(hi[..., :-2], hi[..., 1:-1]), hi[..., 2:])
    mid = _median3(mid[..., :-2], mid[..., 1:-1], mid[..., 2:])
    return _median3(lo, mid, hi)


def _median3(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    return torch.maximum(torch.minimum(a, b), torch.minimum(torch.maximum(a, b), c))



def recent_observation(surface: torch.Tensor, last_us: torch.Tensor, origin: torch.Tensor, size: tuple[int, int],
                       t_now_us: torch.Tensor, max_age_us: int = 0,
                       recency_us: float | torch.Tensor = 0.0) -> torch.Tensor:
    """The matching observation (:func:`observation`) of one window of each surface, weighed by event age.

    Every pixel of the window is ``S * [age < max_age_us] * exp(-max(age, 0) / recency_us)`` before the 3x3
    median (mirror border at the window's edges), with ``age = t_now_us - last_us`` of its newest event of
    any polarity (each factor only when its parameter is positive). One compiled pass per window.

    Args:
        surface: ``(B, H, W)`` float32 EROS; last_us: ``(B, C, H, W)`` int64 time surface (microseconds).
        origin: ``(B, 2)`` int64 top-left pixel ``(u0, v0)`` of each window; size: ``(h, w)``, inside the frame.
        t_now_us: ``(B,)`` int64 current time per element.
        recency_us: one recency window for all elements, or ``(B,)`` one per element (microseconds, ``>= 0``).

    Shape: returns ``(B, h, w)`` float32.
    """
    B, H, W = surface.shape
    h, w = size
    _check_time_surface(last_us, B, H, W)
    o = origin.long()
    if o.shape != (B, 2) or not (h > 0 and w > 0) or bool(((o < 0) | (o + torch.tensor([w, h]) > torch.tensor([W, H]))).any()):
        raise ValueError(f"windows of size {(h, w)} at origins {o.tolist()} must lie inside the {H}x{W} surface")
    out = torch.empty(B, h, w, dtype=torch.float32)
    _recent_kernel(surface.detach().numpy(), last_us.detach().numpy(), o.contiguous().numpy(),  # views: no copies
                   t_now_us.long().contiguous().numpy(), int(max_age_us), *recency_arrays(recency_us, B, max_age_us),
                   out.numpy())
    return out


def canvas_observation(surface: torch.Tensor, last_us: torch.Tensor, box: torch.Tensor, canvas: int,
                       t_now_us: torch.Tensor, max_age_us: int = 0,
                       recency_us: float | torch.Tensor = 0.0) -> torch.Tensor:
    """:func:`recent_observation` of the frame under each canvas box, resampled into the canvas.

    Canvas pixel ``i`` (column or row) samples frame coordinate ``c + (i + 0.5 - canvas / 2) side / canvas`` of
    the box ``[cu, cv, side]`` (bilinear, zero outside the frame), as
    :func:`torchevtrack.stages.template.to_canvas` does. The observation is made over the smallest window of
    the frame holding every tap (its median mirrors at that window's edges), in one compiled pass per element.

    Args:
        surface, last_us, t_now_us, max_age_us, recency_us: see :func:`recent_observation`.
        box: ``(B, 3)`` float64 ``[cu, cv, side]`` frame pixels; canvas: side ``N`` of the canvas, pixels.

    Shape: returns ``(B, N, N)`` float32.
    """
    B, H, W = surface.shape
    _check_time_surface(last_us, B, H, W)
    if box.shape != (B, 3):
        raise ValueError(f"box must have shape ({B}, 3) [cu, cv, side], got {tuple(box.shape)}")
    out = torch.empty(B, canvas, canvas, dtype=torch.float32)
    canvas_kernel(surface.detach().numpy(), last_us.detach().numpy(), box.double().contiguous().numpy(),
                  t_now_us.long().contiguous().numpy(), int(max_age_us), *recency_arrays(recency_us, B, max_age_us),
                  out.numpy())
    return out


def _check_time_surface(last_us: torch.Tensor, B: int, H: int, W: int) -> None:
    if last_us.shape[0] != B or last_us.shape[2:] != (H, W) or last_us.dtype != torch.int64:
        raise ValueError(f"last_us must be an int64 ({B}, C, {H}, {W}) time surface, got {last_us.dtype} "
                         f"{tuple(last_us.shape)}")


class RecencyArrays(NamedTuple):
    """The recency windows of a batch, as the compiled observation takes them: the distinct windows ``taus`` ``(L,)``
    float64 us (0: no weighting), their age weights ``decay`` ``(L, n)`` float32 (:func:`decay_tables`) and each
    element's window ``level`` ``(B,)`` int64, a row of both (a view of :class:`Recency`'s buffer, read at each
    call, or made once by :func:`recency_arrays`)."""

    taus: np.ndarray
    decay: np.ndarray
    level: np.ndarray


def recency_arrays(recency_us: float | torch.Tensor, B: int, max_age_us: int) -> RecencyArrays:
    """:class:`RecencyArrays` of one window for all ``B`` elements (a number) or of one per element (``(B,)``),
    microseconds, ``>= 0``."""
    r = torch.as_tensor(recency_us, dtype=torch.float64)
    if r.ndim == 0:
        r = r.expand(B)
    if r.shape != (B,) or not bool(((r >= 0) & torch.isfinite(r)).all()):
        raise ValueError(f"recency_us must be one number or ({B},) numbers, finite and >= 0 (microseconds), got "
                         f"{recency_us!r}")
    taus, level = torch.unique(r, return_inverse=True)
    taus = tuple(taus.tolist())
    return RecencyArrays(np.array(taus), decay_tables(taus, int(max_age_us)), level.numpy())


@functools.lru_cache(maxsize=8)
def decay_tables(taus: tuple[float, ...], max_age: int) -> np.ndarray:
    """The age weights ``exp(-age / tau)`` (float32, :func:`_decay`) of the ages ``0 .. n - 1`` us, one row per
    window ``tau`` (us), for the ``decay`` argument of :func:`canvas_kernel`: ``n`` the ages that can carry weight
    (below ``max_age`` us, if positive) up to ``16 tau`` of the longest window and at most ``_DECAY_TABLE`` entries;
    no entries if every ``tau <= 0`` (no weights; a row of such a ``tau`` is never read). Cached and read-only.

    Shape: ``(L, n)`` float32, ``L = len(taus)``.
    """
    top = max(taus)
    n = 0 if top <= 0 else min(max_age if max_age > 0 else math.ceil(16 * top), _DECAY_TABLE)
    table = np.empty((len(taus), n), dtype=np.float32)
    for row, tau in zip(table, taus):
        _decay_fill(np.float32(1.0 / tau) if tau > 0 else np.float32(0.0), row)
    table.flags.writeable = False
    return table


_DECAY_TABLE = 1 << 16  # 256 KiB


@kernel
def _decay_fill(inv_tau, out):
    for a in range(len(out)):
        out[a] = _decay(a, inv_tau)
    return out


@kernel
def _decay(age, inv_tau):
    """Weight ``exp(-age / tau)`` of an event ``age`` us old (float32; ``inv_tau = 1 / tau`` float32)."""
    return np.float32(math.exp(-np.float32(age) * inv_tau))


@kernel
def _recent_kernel(surface, last, origin, t_now, max_age, taus, decay, level, out):
    """:func:`recent_observation` into ``out`` ``(B, h, w)``."""
    every_row = np.ones(out.shape[1], dtype=np.bool_)
    for b in range(out.shape[0]):
        k = level[b]
        _recent_window(surface[b], last[b], origin[b, 0], origin[b, 1], t_now[b], max_age, taus[k], decay[k], out[b],
                       every_row)


@kernel
def canvas_kernel(surface, last, box, t_now, max_age, taus, decay, level, out):
    """:func:`canvas_observation` on numpy arrays, unchecked, into ``out``; releases the GIL.

    Args: ``surface`` ``(B, H, W)`` float32 EROS, ``last`` ``(B, C, H, W)`` int64 time surface (us), ``box``
    ``(B, 3)`` float64 ``[cu, cv, side]`` frame pixels, ``t_now`` ``(B,)`` int64 us, ``max_age`` int us, ``taus,
    decay, level`` the recency windows (:class:`RecencyArrays`); ``out`` ``(B, N, N)`` float32, overwritten.
    """
    B, N = out.shape[0], out.shape[1]
    H, W = surface.shape[1], surface.shape[2]
    for b in range(B):
        step = box[b, 2] / N
        first, last_tap = (0.5 - N / 2) * step, (N - 0.5 - N / 2) * step
        u0, v0 = max(math.floor(box[b, 0] + first), 0), max(math.floor(box[b, 1] + first), 0)
        u1, v1 = min(math.floor(box[b, 0] + last_tap) + 2, W), min(math.floor(box[b, 1] + last_tap) + 2, H)
        out[b] = 0.0
        if u1 <= u0 or v1 <= v0:
            continue
        win = np.empty((v1 - v0, u1 - u0), dtype=np.float32)
        x0, x1, wu0, wu1 = canvas_taps(box[b, 0] - u0, step, N, u1 - u0)
        y0, y1, wv0, wv1 = canvas_taps(box[b, 1] - v0, step, N, v1 - v0)
        rows = np.zeros(v1 - v0, dtype=np.bool_)
        for i in range(N):
            rows[y0[i]] = rows[y1[i]] = True
        k = level[b]
        _recent_window(surface[b], last[b], u0, v0, t_now[b], max_age, taus[k], decay[k], win, rows)
        _bilinear(win, x0, x1, wu0, wu1, y0, y1, wv0, wv1, out[b])


@kernel
def _bilinear(img, x0, x1, wu0, wu1, y0, y1, wv0, wv1, out):
    """``out[i, j]`` = ``img`` at the canvas pixel of the taps ``y0, y1, wv0, wv1`` (row ``i``) and ``x0, x1, wu0,
    wu1`` (column ``j``) of :func:`~torchevtrack.stages.canvas_taps`, bilinear, zero outside ``img``. A tap outside
    ``img`` reads a pixel inside with weight 0 (``img >= 0``, so it adds ``+0.0``: the sum is that of the inside taps
    alone); only the tapped pixels of ``img`` are read."""
    N = out.shape[0]
    for i in range(N):
        ya, yb, wa, wb = y0[i], y1[i], wv0[i], wv1[i]
        for j in range(N):
            xa, xb = x0[j], x1[j]
            acc = 0.0
            acc += wa * wu0[j] * img[ya, xa]
            acc += wa * wu1[j] * img[ya, xb]
            acc += wb * wu0[j] * img[yb, xa]
            acc += wb * wu1[j] * img[yb, xb]
            out[i, j] = acc


@kernel
def _recent_window(surface, last, u0, v0, t_now, max_age, tau, decay, out, rows):
    """The age-weighted, 3x3-median observation of one element's window at ``(u0, v0)`` into ``out`` ``(h, w)``
    (:func:`recent_observation`) in the rows marked True in ``rows`` ``(h,)`` (the other rows of ``out`` are left
    as they were: a canvas reads about half the rows of a window twice its size);
    ``surface`` ``(H, W)``, ``last`` ``(C, H, W)``, ``tau`` the recency window (us), ``decay`` the weights of its first
    ages (a row of :func:`decay_tables`)."""
    h, w = out.shape
    C = last.shape[0]
    buf = np.empty((h + 2, w + 2), dtype=np.float32)  # the weighted window, mirror-padded by one pixel
    lo = np.empty(w + 2, dtype=np.float32)  # per column of one row: min, median, max of rows y - 1 .. y + 1
    mid = np.empty(w + 2, dtype=np.float32)
    hi = np.empty(w + 2, dtype=np.float32)
    weighted = np.zeros(h, dtype=np.bool_)  # the rows a marked row's median reads
    for y in range(h):
        if rows[y]:
            weighted[max(y - 1, 0):min(y + 2, h)] = True
    inv_tau = np.float32(1.0 / tau) if tau > 0 else np.float32(0.0)
    if C == 1 and max_age > 0 and tau > 0 and len(decay) >= max_age:
        # one channel and every age below max_age in the table (the tracker's defaults): the same weights without
        # branches, a loop the compiler vectorises (a zero EROS value stays zero whatever its weight)
        top, zero = max_age - 1, np.float32(0.0)
        for y in range(h):
            if not weighted[y]:
                continue
            srow, lrow, brow = surface[v0 + y, u0:u0 + w], last[0, v0 + y, u0:u0 + w], buf[y + 1, 1:w + 1]
            for x in range(w):
                age = t_now - lrow[x]
                brow[x] = srow[x] * decay[min(max(age, 0), top)] if age < max_age else zero
    else:
        for y in range(h):
            if not weighted[y]:
                continue
            for x in range(w):
                s = surface[v0 + y, u0 + x]
                if s != 0 and (max_age > 0 or tau > 0):
                    newest = last[0, v0 + y, u0 + x]
                    for c in range(1, C):
                        newest = max(newest, last[c, v0 + y, u0 + x])
                    age = t_now - newest
                    if max_age > 0 and age >= max_age:
                        s = np.float32(0.0)
                    elif tau > 0:
                        age = max(age, 0)
                        s = s * (decay[age] if age < len(decay) else _decay(age, inv_tau))
                buf[y + 1, x + 1] = s
    # mirror border (edge not repeated); a window with a one-pixel side repeats its edges instead
    m = 1 if min(h, w) > 1 else 0
    for y in range(1, h + 1):
        buf[y, 0], buf[y, w + 1] = buf[y, 1 + m], buf[y, w - m]
    for x in range(w + 2):
        buf[0, x], buf[h + 1, x] = buf[1 + m, x], buf[h - m, x]
    for y in range(h):
        if not rows[y]:
            continue
        for x in range(w + 2):
            a, c, d = buf[y, x], buf[y + 1, x], buf[y + 2, x]
            p, q = min(a, c), max(a, c)
            p, d = min(p, d), max(p, d)
            lo[x], mid[x], hi[x] = p, min(q, d), max(q, d)
        for x in range(w):
            L = max(max(lo[x], lo[x + 1]), lo[x + 2])
            Hh = min(min(hi[x], hi[x + 1]), hi[x + 2])
            m0, m1, m2 = mid[x], mid[x + 1], mid[x + 2]
            M = max(min(m0, m1), min(max(m0, m1), m2))
            out[y, x] = max(min(L, M), min(max(L, M), Hh))


class EROS(nn.Module):
    """Stateful EROS surface for ``B`` independent event streams.

    Args:
        height, width: sensor size in pixels.
        kernel_size: odd window size ``k`` (default 7).
        decay: ``d`` in ``(0, 1)`` (default 0.3); per-event factor ``d ** (1 / k)``.
        batch_size: number of independent streams ``B``.

    Buffers:
        surface: ``(B, H, W)`` float32 in ``[0, 1]``, initially 0.

    Call ``forward(x, y, b=None)`` with a packet of events (time order within each batch element); it
    updates ``surface`` and returns it (the buffer itself, not a copy). ``forward(x, y, b, rows=slice)`` takes the
    events of the batch elements ``rows`` only (``b`` counted from ``rows.start``) and returns their rows: threads
    may update disjoint rows at once.
    """

    surface: torch.Tensor

    def __init__(self, height: int, width: int, kernel_size: int = ErosConfig.kernel_size,
                 decay: float = ErosConfig.decay, batch_size: int = 1):
        super().__init__()
        _check_params(kernel_size, decay)
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        self.kernel_size = kernel_size
        self.decay = float(decay)
        self.register_buffer("surface", torch.zeros(batch_size, height, width, dtype=torch.float32))

    @classmethod
    def from_config(cls, height: int, width: int, cfg: ErosConfig, batch_size: int = 1) -> "EROS":
        """The EROS of the config section ``eros`` (:class:`~torchevtrack.config.ErosConfig`) for ``B`` streams."""
        return cls(height, width, cfg.kernel_size, cfg.decay, batch_size=batch_size)

    @property
    def lam(self) -> float:
        """Per-event decay factor ``decay ** (1 / kernel_size)``."""
        return self.decay ** (1.0 / self.kernel_size)

    def forward(self, x: torch.Tensor, y: torch.Tensor, b: torch.Tensor | None = None,
                rows: slice | None = None) -> torch.Tensor:
        surface = self.surface if rows is None else self.surface[rows]
        return eros_update_(surface, x, y, b, self.kernel_size, self.decay)

    def observation(self) -> torch.Tensor:
        """3x3 median blur of the current surface, ``(B, H, W)``."""
        return observation(self.surface)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Clear the surface of every element, or of those selected by ``mask`` (``(B,)`` bool or
        ``(K,)`` indices, see :func:`~torchevtrack.stages.batch_mask`); the others are untouched."""
        if mask is None:
            self.surface.zero_()
        else:
            self.surface.masked_fill_(batch_mask(mask, self.surface.shape[0])[:, None, None], 0.0)

    def extra_repr(self) -> str:
        B, H, W = self.surface.shape
        return f"height={H}, width={W}, kernel_size={self.kernel_size}, decay={self.decay}, batch_size={B}"


def time_surface_update_(last_us: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor,
                         b: torch.Tensor | None = None) -> torch.Tensor:
    """Apply events to a timestamp surface in place and return it: ``last_us[b, y, x] = max(last_us[b, y, x], t)``.

    Shape:
        last_us: ``(B, H, W)`` int64 microseconds (:data:`~torchevtrack.stages.NEVER` where no event has been).
        x, y: ``(N,)`` integer pixels; t: ``(N,)`` int64 microseconds; b: ``(N,)`` batch index or ``None``.

    Raises:
        TypeError / ValueError: as :func:`prepare_events`, and for ``t`` not int64 ``(N,)``.
    """
    if not isinstance(last_us, torch.Tensor) or last_us.dtype != torch.int64 or last_us.ndim != 3 \
            or not last_us.is_contiguous():
        raise ValueError("last_us must be a contiguous int64 (B, H, W) tensor, got "
                         f"{getattr(last_us, 'dtype', type(last_us).__name__)} {tuple(getattr(last_us, 'shape', ()))}")
    check_fields(x, y, b)
    check_times(t, x.shape)
    bn = np.zeros(1, dtype=np.int64) if b is None else b.numpy()
    if not time_kernel(last_us.numpy(), x.numpy(), y.numpy(), t.numpy(), bn, b is not None):
        prepare_events(x, y, b, *last_us.shape[1:], last_us.shape[0])  # raises the range error
    return last_us


@kernel
def time_kernel(last, x, y, t, b, batched):
    """:func:`time_surface_update_` on numpy arrays, unchecked, for compiled callers: the events ``x, y, t`` ``(N,)``
    (``t`` int64 us) of the elements ``b`` (read only when ``batched``) into ``last`` ``(B, H, W)`` int64. Returns
    False, the surface untouched, if an event lies outside it."""
    B, H, W = last.shape
    if not events_inside(x, y, b, batched, B, H, W):
        return False
    flat = last.reshape(B * H * W)
    n = x.shape[0]
    for i in range(n):
        j = i + AHEAD
        if j < n:
            prefetch(flat, ((b[j] if batched else 0) * H + y[j]) * W + x[j])
        k = b[i] if batched else 0
        last[k, y[i], x[i]] = max(last[k, y[i], x[i]], t[i])
    return True


class TimeSurface(nn.Module):
    """The time of the newest event at each pixel, of either polarity, for ``B`` event streams.

    The observation (:func:`canvas_observation`) weighs the EROS by it. The flow keeps a surface of its own (one
    channel per polarity, padded), which its matching writes as it reads, so this one lets the EROS side observe
    while the flow runs (the tracker's pipeline).

    Args:
        height, width: sensor size in pixels; batch_size: number of streams ``B``.

    Buffers:
        last_us: ``(B, H, W)`` int64 microseconds, :data:`~torchevtrack.stages.NEVER` where no event has been.

    ``forward(x, y, t, b=None, rows=None)`` applies a packet (``b`` counted from ``rows.start``) and returns
    ``last_us`` (of ``rows``), the buffer itself.

    Example:
        >>> import torch
        >>> ts = TimeSurface(2, 3)
        >>> ts(torch.tensor([1, 1]), torch.tensor([0, 0]), torch.tensor([40, 70]))[0, 0].tolist()[1]
        70
    """

    last_us: torch.Tensor

    def __init__(self, height: int, width: int, batch_size: int = 1):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        self.register_buffer("last_us", torch.full((batch_size, height, width), NEVER, dtype=torch.int64))

    def forward(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, b: torch.Tensor | None = None,
                rows: slice | None = None) -> torch.Tensor:
        return time_surface_update_(self.last_us if rows is None else self.last_us[rows], x, y, t, b)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget the events of every element, or of those selected by ``mask`` (``(B,)`` bool or ``(K,)``
        indices, see :func:`~torchevtrack.stages.batch_mask`)."""
        if mask is None:
            self.last_us.fill_(NEVER)
        else:
            self.last_us.masked_fill_(batch_mask(mask, self.last_us.shape[0])[:, None, None], NEVER)

    def extra_repr(self) -> str:
        B, H, W = self.last_us.shape
        return f"height={H}, width={W}, batch_size={B}"


MIN_FLOW_VECTORS = 3  # valid flow vectors an element needs for its speed to set its window
# The image speed is this percentile of the valid blocks' flow speeds: a normal flow is the edge's speed times the
# |cos| of the angle between the motion and the edge's normal, so its median under-reads the speed (|cos 45 deg| =
# 0.71 for angles spread evenly) and its upper quartile reads 0.92 of it.
SPEED_PERCENTILE = 75.0


def follow_speed(flow: torch.Tensor, valid: torch.Tensor, px: float, min_us: float, max_us: float) -> torch.Tensor:
    """The recency window in which the edges move ``px`` pixels: ``px / v`` with ``v`` the upper quartile
    (:data:`SPEED_PERCENTILE`) of the speeds of an element's valid flow vectors, clamped to ``[min_us, max_us]`` and
    rounded to a multiple of :data:`~torchevtrack.config.RECENCY_STEP_US` above ``min_us``; NaN for an element with
    fewer than :data:`MIN_FLOW_VECTORS` valid vectors (its speed is not known).

    Args:
        flow: ``(B, G, 2)`` float32 flow, pixels/s (:class:`~torchevtrack.stages.flow.FlowField`); valid: ``(B, G)``
            bool; px: pixels (> 0); min_us, max_us: microseconds, ``0 < min_us <= max_us``.

    Shape: returns ``(B,)`` float64 microseconds.

    Example:
        >>> import torch
        >>> flow = torch.tensor([[[500.0, 0.0], [0.0, 400.0], [300.0, 400.0], [9.0, 9.0]]])
        >>> follow_speed(flow, torch.tensor([[True, True, True, False]]), 2.5, 1250.0, 10000.0)  # 400, 500, 500 px/s
        tensor([5000.], dtype=torch.float64)
    """
    level = np.full(flow.shape[0], -1, dtype=np.int64)
    _follow_kernel(flow.numpy(), valid.numpy(), float(px), float(min_us), float(max_us), level)
    return torch.from_numpy(np.where(level >= 0, min_us + RECENCY_STEP_US * level, np.nan))


@kernel
def _follow_kernel(flow, valid, px, min_us, max_us, level):
    """:func:`follow_speed` as the index of each window on the grid into ``level`` ``(B,)`` int64 (left as it is for
    an element without enough vectors): :meth:`Recency.forward`."""
    speed = np.empty(valid.shape[1], dtype=np.float64)
    for b in range(valid.shape[0]):
        n = 0
        for g in range(valid.shape[1]):
            if valid[b, g]:
                speed[n] = math.hypot(np.float64(flow[b, g, 0]), np.float64(flow[b, g, 1]))
                n += 1
        if n >= MIN_FLOW_VECTORS:
            tau = min(max(px / max(np.percentile(speed[:n], SPEED_PERCENTILE), 1e-6) * 1e6, min_us), max_us)
            level[b] = round((tau - min_us) / RECENCY_STEP_US)


class Recency(nn.Module):
    """The observation's recency window (``tau`` of ``exp(-age / tau)``, :func:`canvas_observation`) per element.

    Fixed (``px = 0``): every element's window is ``recency_us``. Following the image speed (``px > 0``): each call
    sets an element's window to :func:`follow_speed` of its flow (an element without enough flow vectors keeps its
    window), so that the observation holds about ``px`` pixels of each edge's motion: long windows when the object
    is slow (more of its edges), short ones when it is fast (no smear). An element starts, and restarts at
    :meth:`reset`, at ``recency_us``.

    Args:
        batch_size: ``B``; recency_us: the fixed or starting window (microseconds, ``>= 0``, 0: no weighting);
        px: pixels of motion a window holds (0, or ``recency_us = 0``: fixed); min_us, max_us: the window's bounds
            when it follows the speed, multiples of :data:`~torchevtrack.config.RECENCY_STEP_US` with ``recency_us``
            a multiple between them.

    Buffers:
        level: ``(B,)`` int64, each element's window as an index into :attr:`windows_us`.

    ``forward(flow (B, G, 2) float32 px/s, valid (B, G) bool)`` updates the windows from a flow field and returns
    :attr:`window_us`.

    Example:
        >>> import torch
        >>> rec = Recency(1, 2500.0, px=2.5, min_us=1250, max_us=10000)
        >>> rec(torch.tensor([[[1000.0, 0.0]] * 3]), torch.ones(1, 3, dtype=torch.bool))  # 2.5 px at 1000 px/s
        tensor([2500.], dtype=torch.float64)
        >>> rec(torch.tensor([[[600.0, 0.0]] * 3]), torch.ones(1, 3, dtype=torch.bool)).tolist()  # 4167 us, rounded
        [4250.0]
    """

    level: torch.Tensor

    def __init__(self, batch_size: int, recency_us: float, *, px: float = 0.0, min_us: float = 1250.0,
                 max_us: float = 10000.0):
        super().__init__()
        self.windows_us = recency_windows(recency_us, px, min_us, max_us)
        # a single window (px 0, or recency_us 0: no weighting, nothing to follow) is fixed
        self.px = float(px) if len(self.windows_us) > 1 else 0.0
        self.min_us, self.max_us = float(min_us), float(max_us)
        self.start = self.windows_us.index(float(recency_us))
        self._windows = torch.tensor(self.windows_us, dtype=torch.float64)
        self.register_buffer("level", torch.full((batch_size,), self.start, dtype=torch.int64))

    @classmethod
    def from_config(cls, cfg: ErosConfig, batch_size: int = 1) -> "Recency":
        """The windows of the config section ``eros`` (:class:`~torchevtrack.config.ErosConfig`)."""
        return cls(batch_size, cfg.recency_us, px=cfg.recency_px, min_us=cfg.recency_min_us, max_us=cfg.recency_max_us)

    @property
    def window_us(self) -> torch.Tensor:
        """``(B,)`` float64: each element's window, microseconds."""
        return self._windows[self.level]

    def forward(self, flow: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        B = self.level.shape[0]
        if flow.ndim != 3 or flow.shape[0] != B or flow.shape[2] != 2 or valid.shape != flow.shape[:2]:
            raise ValueError(f"expected flow ({B}, G, 2) and valid ({B}, G), got {tuple(flow.shape)} and "
                             f"{tuple(valid.shape)}")
        if self.px > 0:
            _follow_kernel(flow.numpy(), valid.numpy(), self.px, self.min_us, self.max_us, self.level.numpy())
        return self.window_us

    def bind(self) -> Callable[[np.ndarray, np.ndarray], None]:
        """:meth:`forward` on numpy arrays, unchecked and returning nothing, bound to the ``level`` buffer (a view,
        written in place): the tracker's step (a few microseconds; nothing to do for a fixed window)."""
        if self.px == 0:
            return lambda flow, valid: None
        level, px, lo, hi = self.level.numpy(), self.px, self.min_us, self.max_us
        return lambda flow, valid: _follow_kernel(flow, valid, px, lo, hi, level)

    def arrays(self, max_age_us: int, rows: slice = slice(None)) -> RecencyArrays:
        """The windows of the elements ``rows`` for the compiled observation (the level a view of the buffer)."""
        return RecencyArrays(np.array(self.windows_us), decay_tables(self.windows_us, int(max_age_us)),
                             self.level[rows].numpy())

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Every element's window, or those selected by ``mask`` (``(B,)`` bool or ``(K,)`` indices), back to
        ``recency_us``."""
        if mask is None:
            self.level.fill_(self.start)
        else:
            self.level.masked_fill_(batch_mask(mask, self.level.shape[0]), self.start)

    def extra_repr(self) -> str:
        return (f"batch_size={self.level.shape[0]}, recency_us={self.windows_us[self.start]}, px={self.px}" +
                (f", min_us={self.min_us}, max_us={self.max_us}" if self.px > 0 else ""))


def bind_observe(eros: EROS, time_surface: TimeSurface, recency: RecencyArrays, *, canvas: int,
                 max_age_us: int = 0) -> Callable[..., np.ndarray | None | bool]:
    """``eros(x, y, b)``, ``time_surface(x, y, t, b)`` and then :func:`canvas_observation` under a box, in one
    compiled call that releases the GIL, bound to the stages' buffers (numpy views, written in place at each call).

    The tracker's pipeline thread runs it in streaming, while the calling thread runs the flow: these stages read only
    their own state and the events. Returns ``run(x, y, t, b, box, t_now_us)`` of numpy arrays, unchecked: packed
    events ``(N,)`` (``t`` int64 us; ``b`` ``None``: all in element 0), the canvas boxes ``box`` ``(B, 3)`` float64
    ``[cu, cv, side]`` (or ``None``: no observation) and ``t_now_us`` ``(B,)`` int64. ``run`` gives the observation
    ``(B, canvas, canvas)`` float32 (``None`` without a box), or ``False``, nothing written, if an event lies outside
    the surfaces. ``recency``: each element's recency window (:meth:`Recency.arrays`, read at each call);
    ``max_age_us``: as for :func:`canvas_observation`.
    """
    s, last = eros.surface.numpy(), time_surface.last_us.numpy()
    if s.shape != last.shape:
        raise ValueError(f"the EROS and the time surface must have the same shape, got {s.shape} and {last.shape}")
    lam, r = s.dtype.type(eros.lam), eros.kernel_size // 2
    max_age_us = int(max_age_us)
    if recency.level.shape != (s.shape[0],):
        raise ValueError(f"recency has {recency.level.shape[0]} elements, the EROS {s.shape[0]}")
    none, no_box = np.zeros(1, dtype=np.int64), np.empty((0, 3))

    def run(x: np.ndarray, y: np.ndarray, t: np.ndarray, b: np.ndarray | None, box: np.ndarray | None,
            t_now_us: np.ndarray) -> np.ndarray | None | bool:
        obs = np.empty((s.shape[0] if box is not None else 0, canvas, canvas), dtype=np.float32)
        if not _observe_kernel(s, lam, r, last, x, y, t, none if b is None else b, b is not None,
                               no_box if box is None else box, t_now_us, max_age_us, *recency, obs):
            return False
        return obs if box is not None else None
    return run


@kernel
def _observe_kernel(surface, lam, r, last, x, y, t, b, batched, box, t_now, max_age, taus, decay, level, out):
    """:func:`eros_kernel` and :func:`time_kernel`, then (if ``box`` has rows) :func:`canvas_kernel` into ``out``;
    False, nothing written, if an event lies outside the surfaces."""
    if x.shape[0]:
        if not eros_kernel(surface, x, y, b, batched, r, lam):
            return False
        time_kernel(last, x, y, t, b, batched)
    if box.shape[0]:
        B, H, W = last.shape
        canvas_kernel(surface, last.reshape(B, 1, H, W), box, t_now, max_age, taus, decay, level, out)
    return True
