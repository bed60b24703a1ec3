"""Stage 2: event optical flow by spatio-temporal triplet matching and per-block registration.

Surface of active events (SAE): the last event time (int64 us) per pixel, optionally one channel per
polarity; a pixel that never fired holds :data:`NEVER`.

Triplets. For an event ``e0 = (p0, t0)`` and an offset ``d = (dx, dy)``, ``|dx|, |dy| <= D``, ``d != 0``
(``D = 2``: 24 directions), let ``p1 = p0 + d``, ``p2 = p0 + 2 d`` and ``t1, t2`` their SAE times,
``dt01 = t0 - t1``, ``dt12 = t1 - t2``. The triplet is accepted when ``0 < dt01 < dt_max``,
``dt12 > 0`` and ``|1 - dt12 / dt01| < tol``; its flow sample is ``F = (p0 - p2) / (t0 - t2) =
-2 d / (dt01 + dt12)`` pixel/s (an edge moving along +x at ``v`` px/s gives ``(+v, 0)``).

Which SAE an event sees (exact, causal): the SAE as it was before the packet, updated with every
*strictly earlier* event of the packet (packed order, same batch element, same polarity channel) -
what a per-event loop that looks up, then writes ``SAE[p0] = t0``, sees. It is computed without a loop:
for a looked-up pixel ``q`` with first / last packet events ``F(q)`` / ``L(q)``, the seen time is the
old SAE if ``F(q) >= e``, the SAE after the packet if ``L(q) < e``, and otherwise (rare) the time of
the last packet event at ``q`` before ``e``, found by ``searchsorted`` on the packet sorted by
``(pixel, index)``. Pixels outside the image never fired.

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

Memory: the triplet search holds about 3 kB per event. :class:`TripletFlow` matches a packet longer
than ``chunk`` events (a burst) chunk by chunk, each chunk against the SAE updated with the earlier
chunks, then registers all samples together. Since every event sees exactly the strictly earlier
events, the samples, the SAE and the flow field are those of one pass, bit for bit (for time-ordered
elements, where the last event at a pixel is also its latest); the samples themselves are few (about
0.5 per event on noise bursts).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as Fnn
from torch import nn

from torchevtrack.stages import batch_mask
from torchevtrack.stages.eros import prepare_events

__all__ = [
    "NEVER",
    "FlowField",
    "TripletFlow",
    "block_grid",
    "register_blocks",
    "sae_update",
    "sae_update_",
    "triplet_samples",
]

NEVER = -(2 ** 62)
"""SAE value of a pixel that never fired (int64 microseconds)."""


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


def _prepare(sae: torch.Tensor, x, y, t, p, b):
    _check_sae(sae)
    B, C, H, W = sae.shape
    xi, yi, bi = prepare_events(x, y, b, H, W, B)
    if not isinstance(t, torch.Tensor) or t.dtype != torch.int64 or t.shape != xi.shape:
        raise TypeError(f"t must be an int64 tensor of microseconds with the shape of x {tuple(xi.shape)}")
    if C == 1:
        ci = torch.zeros_like(xi)
    else:
        if not isinstance(p, torch.Tensor) or p.shape != xi.shape or p.is_floating_point():
            raise TypeError(f"p must be an integer tensor with the shape of x {tuple(xi.shape)}")
        ci = p.long()
        if ci.numel() and bool(((ci < 0) | (ci > 1)).any()):
            raise ValueError("p must be in {0, 1}")
    return xi, yi, bi * C + ci


def sae_update_(sae: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None,
                b: torch.Tensor | None = None) -> torch.Tensor:
    """In place: ``sae[b, c, y, x] = max(sae, t)`` per event (``c = p`` if two channels, else 0); returns ``sae``.

    Shape:
        sae: ``(B, C, H, W)`` int64 us, ``C`` in ``{1, 2}``; x, y, t, p, b: ``(N,)``.
    """
    xi, yi, ch = _prepare(sae, x, y, t, p, b)
    _, _, H, W = sae.shape
    sae.view(-1).scatter_reduce_(0, (ch * H + yi) * W + xi, t, "amax")
    return sae


def sae_update(sae, x, y, t, p, b=None) -> torch.Tensor:
    """Out-of-place :func:`sae_update_`."""
    return sae_update_(sae.clone(), x, y, t, p, b)


def _seen_times(sae_pad: torch.Tensor, q: torch.Tensor, e: torch.Tensor, n: int, t: torch.Tensor,
                first: torch.Tensor, last: torch.Tensor, keys: torch.Tensor, t_sorted: torch.Tensor) -> torch.Tensor:
    """SAE time at padded flat pixel ``q`` as seen by packet event ``e`` (see the module docstring)."""
    f, l_ = first.index_select(0, q), last.index_select(0, q)
    out = torch.where(f >= e, sae_pad.index_select(0, q), t.index_select(0, l_.clamp(min=0)))
    partial = ((f < e) & (l_ >= e)).nonzero().squeeze(1)
    if partial.numel():
        pos = torch.searchsorted(keys, q.index_select(0, partial).long() * n + e.index_select(0, partial)) - 1
        out[partial] = t_sorted.index_select(0, pos)
    return out


def _pad_sae(sae: torch.Tensor, pad: int) -> torch.Tensor:
    B, C, H, W = sae.shape
    out = torch.full((B, C, H + 2 * pad, W + 2 * pad), NEVER, dtype=torch.int64)
    out[:, :, pad:pad + H, pad:pad + W] = sae
    return out


def _event_boxes(sae_pad: torch.Tensor, pad: int, xi, yi, ch) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The padded SAE cropped around the events of each (batch, channel) plane, one common box size
    ``(B * C, hb, wb)``, and the events' flat index into it. Every lookup ``p0 + k d`` (``|k d| <= pad``) of
    an event stays inside its plane's box, so the lookups touch a few cache-sized arrays instead of
    full-sensor ones."""
    B, C, Hp, Wp = sae_pad.shape
    planes = B * C
    lo_y = torch.full((planes,), Hp, dtype=torch.long).scatter_reduce_(0, ch, yi, "amin")
    hi_y = torch.full((planes,), -1, dtype=torch.long).scatter_reduce_(0, ch, yi, "amax")
    lo_x = torch.full((planes,), Wp, dtype=torch.long).scatter_reduce_(0, ch, xi, "amin")
    hi_x = torch.full((planes,), -1, dtype=torch.long).scatter_reduce_(0, ch, xi, "amax")
    used = hi_y >= 0
    hb = int(torch.where(used, hi_y - lo_y, 0).max()) + 1 + 2 * pad
    wb = int(torch.where(used, hi_x - lo_x, 0).max()) + 1 + 2 * pad
    y0 = torch.where(used, lo_y, 0).clamp_(max=Hp - hb)  # padded coordinates: event rows lo_y + pad +- pad
    x0 = torch.where(used, lo_x, 0).clamp_(max=Wp - wb)
    start = (torch.arange(planes) * Hp + y0) * Wp + x0
    box = sae_pad.view(-1)[start[:, None, None] + torch.arange(hb)[:, None] * Wp + torch.arange(wb)]
    pe = (ch * hb + yi + pad - y0.index_select(0, ch)) * wb + (xi + pad - x0.index_select(0, ch))
    return box, pe, wb


def _triplets_padded(sae_pad: torch.Tensor, pad: int, xi, yi, ch, t, D: int, dt_max_us: int, tol: float):
    n = xi.numel()
    if n == 0:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, 2)
    box, pe, Wp = _event_boxes(sae_pad, pad, xi, yi, ch)
    flat = box.view(-1)
    # Pixel and event indices of the lookups in int32 (box and packet sizes are far below 2^31): half the
    # memory traffic of int64 for the ~25 n lookups.
    order = torch.arange(n, dtype=torch.int32)
    first = torch.full((flat.numel(),), n, dtype=torch.int32).scatter_reduce_(0, pe, order, "amin")
    last = torch.full((flat.numel(),), -1, dtype=torch.int32).scatter_reduce_(0, pe, order, "amax")
    keys, perm = torch.sort(pe * n + order)
    t_sorted = t.index_select(0, perm)
    dirs = _directions(D)
    K = dirs.shape[0]
    step = (dirs[:, 1] * Wp + dirs[:, 0]).int()  # (K,) flat offset of d
    # Stage 1: p1 for every (event, direction); keep pairs with 0 < dt01 < dt_max.
    q1 = (pe.int()[:, None] + step).view(-1)
    e1 = order[:, None].expand(n, K).reshape(-1)
    t1 = _seen_times(flat, q1, e1, n, t, first, last, keys, t_sorted)
    dt01 = (t[:, None] - t1.view(n, K)).view(-1)
    keep = ((dt01 > 0) & (dt01 < dt_max_us)).nonzero().squeeze(1)
    # Stage 2: p2 = p0 + 2d for the survivors.
    k = keep % K
    ev = torch.div(keep, K, rounding_mode="floor")
    q2 = q1.index_select(0, keep) + step.index_select(0, k)
    t1k = t1.index_select(0, keep)
    t2 = _seen_times(flat, q2, ev.int(), n, t, first, last, keys, t_sorted)
    dt01 = dt01.index_select(0, keep)
    dt12 = t1k - t2
    ok = ((dt12 > 0) & ((1.0 - dt12.double() / dt01.double()).abs() < tol)).nonzero().squeeze(1)
    span = (dt01.index_select(0, ok) + dt12.index_select(0, ok)).double() * 1e-6  # t0 - t2, seconds
    flow = (-2.0 * dirs.index_select(0, k.index_select(0, ok)).double() / span[:, None]).float()
    return ev.index_select(0, ok), flow


def _check_flow_params(D, dt_max_us, tol):
    if isinstance(D, bool) or not isinstance(D, int) or D < 1:
        raise ValueError(f"D must be a positive int, got {D!r}")
    if not dt_max_us > 0:
        raise ValueError(f"dt_max_us must be positive, got {dt_max_us!r}")
    if not tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")


def triplet_samples(sae: torch.Tensor, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor,
                    p: torch.Tensor | None, b: torch.Tensor | None = None, D: int = 2, dt_max_us: int = 50_000,
                    tol: float = 0.125) -> tuple[torch.Tensor, torch.Tensor]:
    """Triplet flow samples of a packet of events against ``sae`` (the SAE before the packet).

    Each event sees ``sae`` updated with the strictly earlier events of the packet (module docstring).
    ``sae`` is not modified.

    Shape:
        sae: ``(B, C, H, W)`` int64 us; x, y, t, p, b: ``(N,)``.
        Returns ``event (S,)`` int64 index into the packet (sorted) and ``flow (S, 2)`` float32 px/s.
    """
    _check_flow_params(D, dt_max_us, tol)
    xi, yi, ch = _prepare(sae, x, y, t, p, b)
    pad = 2 * D
    return _triplets_padded(_pad_sae(sae, pad), pad, xi, yi, ch, t, D, dt_max_us, tol)


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
    count = torch.bincount(block_id, minlength=n_blocks)
    out = torch.zeros(n_blocks, 2, dtype=torch.float32)
    uv_out = torch.full((n_blocks, 2), math.nan, dtype=torch.float32)
    valid = count >= min_samples
    keep = valid[block_id].nonzero().squeeze(1)
    if keep.numel() == 0:
        return out, uv_out, valid, count
    perm = keep[torch.argsort(block_id[keep] * (event.max() + 1) + event[keep], stable=True)]
    g, ev = block_id[perm], event[perm]
    # Rank of each sample's event inside its block, and deterministic event subsampling.
    new_ev = torch.ones_like(ev, dtype=torch.bool)
    new_ev[1:] = (g[1:] != g[:-1]) | (ev[1:] != ev[:-1])
    ev_rank = torch.cumsum(new_ev.long(), 0) - 1
    block_start = torch.ones_like(new_ev)
    block_start[1:] = g[1:] != g[:-1]
    ev_rank = ev_rank - torch.cummax(torch.where(block_start, ev_rank, 0), 0).values
    stride = torch.div(count[g] + max_candidates - 1, max_candidates, rounding_mode="floor")
    sub = (ev_rank % stride == 0).nonzero().squeeze(1)
    perm, g, ev_rank = perm[sub], g[sub], torch.div(ev_rank[sub], stride[sub], rounding_mode="floor")
    # Slot of each kept sample inside its block; truncate to max_candidates.
    idx = torch.arange(g.numel())
    start = torch.ones_like(g, dtype=torch.bool)
    start[1:] = g[1:] != g[:-1]
    slot = idx - torch.cummax(torch.where(start, idx, 0), 0).values
    fit = (slot < max_candidates).nonzero().squeeze(1)
    perm, g, ev_rank, slot = perm[fit], g[fit], ev_rank[fit], slot[fit]
    blocks, row = torch.unique_consecutive(g, return_inverse=True)
    # Blocks are evaluated in groups of similar size (up to 16, 32, 64, ... samples), each padded only to its
    # largest block. Every sum below runs over the padded dimension 1, and such sums do not depend on the
    # amount of zero padding, so a block's result does not depend on the other blocks.
    # Groups are further cut into chunks whose (V, K, K) distance tables stay around 2 MB (cache-sized).
    group, filled = [], {}  # per size class: (chunk index, blocks in that chunk)
    for n in torch.bincount(row).tolist():
        k = max((n - 1) >> 4, 0).bit_length()
        chunk, used = filled.get(k, (0, 0))
        if used * (16 << k) ** 2 * 8 >= 1 << 21:
            chunk, used = chunk + 1, 0
        filled[k] = (chunk, used + 1)
        group.append((k, chunk))
    index = {key: j for j, key in enumerate(sorted(set(group)))}
    group_of = torch.tensor([index[key] for key in group])
    for k in range(len(index)):
        members = (group_of == k).nonzero().squeeze(1)
        local = torch.full((blocks.numel(),), -1, dtype=torch.long)
        local[members] = torch.arange(members.numel())
        at = (group_of[row] == k).nonzero().squeeze(1)
        chosen, uv = _register_group(local[row[at]], slot[at], ev_rank[at], flow[perm[at]], pixel[perm[at]],
                                     members.numel(), tie_tol, estimate, inlier)
        out[blocks[members]] = chosen.float()
        uv_out[blocks[members]] = uv.float()
    return out, uv_out, valid, count


def _register_group(row: torch.Tensor, slot: torch.Tensor, ev_rank: torch.Tensor, flow: torch.Tensor,
                    pixel: torch.Tensor, V: int, tie_tol: float, estimate: str, inlier: float):
    """Registration of ``V`` blocks whose samples sit at ``(row, slot)``; returns flow and uv ``(V, 2)`` float64."""
    K = int(slot.max()) + 1
    cand = torch.zeros(V, K, 2, dtype=torch.float64)
    cand[row, slot] = flow.double()
    pix = torch.zeros(V, K, 2, dtype=torch.float64)
    pix[row, slot] = pixel.double()
    n_ev = torch.zeros(V, dtype=torch.long).scatter_reduce_(0, row, ev_rank + 1, "amax")
    # Event ids per slot; empty slots get E - 1, an id no block uses, so that row only collects zeros.
    E = int(n_ev.max()) + 1
    evs = torch.full((V, K), E - 1, dtype=torch.long)
    evs[row, slot] = ev_rank
    mask = torch.zeros(V, K, dtype=torch.bool)
    mask[row, slot] = True
    # dist[v, j, c] = |cand_c - cand_j| (0 for empty sample slots j); per_ev[v, i, c] = min_{j in event i} of it
    # (0 for no event i); cost[v, c] = sum_i per_ev[v, i, c].
    dist = torch.cdist(cand, cand, compute_mode="use_mm_for_euclid_dist").masked_fill_(~mask[:, :, None], 0.0)
    per_ev = torch.full((V, E, K), math.inf, dtype=torch.float64)
    per_ev.scatter_reduce_(1, evs[:, :, None].expand(V, K, K), dist, "amin").nan_to_num_(posinf=0.0)
    cost = per_ev.sum(1).masked_fill_(~mask, math.inf)
    norm = cand.norm(dim=2)
    near = cost <= cost.min(1, keepdim=True).values + tie_tol * n_ev[:, None] * norm
    spread = dist.sum(1)  # sum_j |F_c - F_j| over the block's samples
    rows = torch.arange(V)
    best = spread.masked_fill_(~near, math.inf).argmin(1)
    chosen = cand[rows, best]
    # Inlier events: their nearest candidate lies within inlier * |F| of the registered F.
    ok_ev = per_ev[rows, :, best] <= inlier * chosen.norm(dim=1, keepdim=True)  # (V, E) by event id
    w = (mask & torch.gather(ok_ev, 1, evs)).double()
    if estimate == "normal":
        # Each sample F_j = -2 d / dt is a line F_j . g = 1 on the time-surface gradient g (s/px); weighted
        # least squares sum_j (F_j . g - 1)^2 / |F_j| (the mean of parallel samples for a single direction).
        # The min-norm solution handles a single sample direction; the normal flow is g / |g|^2.
        wn = w / norm.clamp(min=1e-12)
        A = torch.einsum("vk,vki,vkj->vij", wn, cand, cand)
        rhs = torch.einsum("vk,vki->vi", wn, cand)
        gr = (torch.linalg.pinv(A, hermitian=True) @ rhs[..., None])[..., 0]
        chosen = gr / (gr * gr).sum(1, keepdim=True).clamp(min=1e-30)
    return chosen, (w[..., None] * pix).sum(1) / w.sum(1, keepdim=True)


def _smooth(flow: torch.Tensor, uv: torch.Tensor, valid: torch.Tensor, gy: int, gx: int):
    """Mean flow and mean ``uv`` over the valid blocks of each valid block's 3x3 block neighbourhood."""
    B = flow.shape[0]
    w = valid.to(flow.dtype).view(B, 1, gy, gx)
    both = torch.cat([flow, uv], 2).permute(0, 2, 1).reshape(B, 4, gy, gx)
    num = Fnn.avg_pool2d(both * w, 3, 1, 1, count_include_pad=False)
    den = Fnn.avg_pool2d(w, 3, 1, 1, count_include_pad=False).clamp(min=1e-12)
    sm = (num / den).reshape(B, 4, -1).permute(0, 2, 1)
    sm = torch.where(valid[..., None], sm, torch.cat([flow, uv], 2))
    return sm[..., :2].contiguous(), sm[..., 2:].contiguous()


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
        per_polarity: one SAE channel per polarity (triplets match events of equal polarity only).
        smooth: replace each valid block's flow and ``uv`` by their means over the valid blocks of its 3x3
            block neighbourhood.
        max_candidates, tie_tol, estimate, inlier: see :func:`register_blocks`.
        chunk: a packet of more events is matched this many at a time, in bounded memory and with the
            same result bit for bit (module docstring).

    Buffers:
        sae: ``(B, C, H, W)`` int64 last event time in us (:data:`NEVER` if none), ``C = 2`` if
            ``per_polarity`` else 1.

    ``forward(x, y, t, p, b=None) -> FlowField`` uses only the packet's triplets (matched against the SAE
    history) and then leaves the SAE updated with the packet.
    """

    sae: torch.Tensor

    def __init__(self, height: int, width: int, batch_size: int = 1, block: int = 30, min_samples: int = 20,
                 D: int = 2, dt_max_us: int = 50_000, tol: float = 0.125, per_polarity: bool = False,
                 smooth: bool = False, max_candidates: int = 128, tie_tol: float = 0.02,
                 estimate: str = "normal", inlier: float = 0.25, chunk: int = 2 ** 16):
        super().__init__()
        for name, v in (("height", height), ("width", width), ("batch_size", batch_size), ("block", block),
                        ("min_samples", min_samples), ("max_candidates", max_candidates), ("chunk", chunk)):
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        _check_flow_params(D, dt_max_us, tol)
        if tie_tol < 0 or inlier <= 0 or estimate not in ("register", "normal"):
            raise ValueError("need tie_tol >= 0, inlier > 0 and estimate in {'register', 'normal'}, got "
                             f"{tie_tol!r}, {inlier!r}, {estimate!r}")
        self.height, self.width, self.block = height, width, block
        self.min_samples, self.D, self.dt_max_us, self.tol = min_samples, D, int(dt_max_us), float(tol)
        self.per_polarity, self.smooth = bool(per_polarity), bool(smooth)
        self.max_candidates, self.tie_tol = max_candidates, float(tie_tol)
        self.estimate, self.inlier = estimate, float(inlier)
        self.chunk = chunk
        self.pad = 2 * D
        C = 2 if per_polarity else 1
        self.gy, self.gx, centres = block_grid(height, width, block)
        self.register_buffer("centres", centres, persistent=False)
        # Stored padded by 2D with NEVER so that p1, p2 lookups need no bounds checks.
        self.register_buffer("sae_padded", torch.full((batch_size, C, height + 2 * self.pad, width + 2 * self.pad),
                                                      NEVER, dtype=torch.int64))

    @property
    def sae(self) -> torch.Tensor:
        """``(B, C, H, W)`` view of the SAE."""
        p = self.pad
        return self.sae_padded[:, :, p:p + self.height, p:p + self.width]

    @property
    def n_blocks(self) -> int:
        return self.gy * self.gx

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Forget every element's events, or those of the elements selected by ``mask`` (``(B,)`` bool or
        ``(K,)`` indices, see :func:`~torchevtrack.stages.batch_mask`); the others are untouched."""
        if mask is None:
            self.sae_padded.fill_(NEVER)
        else:
            self.sae_padded.masked_fill_(batch_mask(mask, self.sae_padded.shape[0])[:, None, None, None], NEVER)

    def forward(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, p: torch.Tensor | None = None,
                b: torch.Tensor | None = None) -> FlowField:
        B = self.sae_padded.shape[0]
        G = self.n_blocks
        xi, yi, ch = _prepare(self.sae, x, y, t, p, b)
        C = self.sae_padded.shape[1]
        ev, flow = self._match(xi, yi, ch, t)
        bi = torch.div(ch, C, rounding_mode="floor")
        ex, ey, eb = xi[ev], yi[ev], bi[ev]
        gid = eb * G + torch.div(ey, self.block, rounding_mode="floor") * self.gx + torch.div(
            ex, self.block, rounding_mode="floor")
        out, uv, valid, count = register_blocks(gid, ev, flow, torch.stack([ex, ey], 1), B * G, self.min_samples,
                                                self.max_candidates, self.tie_tol, self.estimate, self.inlier)
        uv = torch.where(valid[:, None], uv, self.centres.repeat(B, 1))
        out, valid, count = out.view(B, G, 2), valid.view(B, G), count.view(B, G)
        uv = uv.view(B, G, 2)
        if self.smooth:
            out, uv = _smooth(out, uv, valid, self.gy, self.gx)
        return FlowField(uv, out, valid, count)

    def _match(self, xi: torch.Tensor, yi: torch.Tensor, ch: torch.Tensor, t: torch.Tensor):
        """Triplet samples of a packet, at most ``chunk`` events at a time, updating the SAE after each chunk
        (a usual window is one chunk; an empty one, one empty chunk).

        Shape: prepared events ``(N,)``; returns ``event (S,)`` (index into the packet) and ``flow (S, 2)``.
        """
        _, _, Hp, Wp = self.sae_padded.shape
        events, flows = [], []
        for s in range(0, max(xi.numel(), 1), self.chunk):
            c = slice(s, s + self.chunk)
            ev, flow = _triplets_padded(self.sae_padded, self.pad, xi[c], yi[c], ch[c], t[c], self.D, self.dt_max_us,
                                        self.tol)
            self.sae_padded.view(-1).scatter_reduce_(0, (ch[c] * Hp + yi[c] + self.pad) * Wp + xi[c] + self.pad, t[c],
                                                     "amax")
            events.append(ev + s)
            flows.append(flow)
        return torch.cat(events), torch.cat(flows)

    def extra_repr(self) -> str:
        return (f"height={self.height}, width={self.width}, block={self.block}, min_samples={self.min_samples}, "
                f"D={self.D}, dt_max_us={self.dt_max_us}, tol={self.tol}, per_polarity={self.per_polarity}, "
                f"smooth={self.smooth}, estimate={self.estimate!r}")
