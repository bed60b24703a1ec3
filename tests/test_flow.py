"""Triplet flow against a sequential per-event oracle, analytic moving edges and a rotating bar."""

import math

import numpy as np
import pytest
import torch

from torchevtrack.stages.flow import (NEVER, TripletFlow, block_grid, register_blocks, sae_update,
                                      triplet_samples)


# ----------------------------------------------------------------------------------------------- oracles
def triplet_oracle(sae0, xs, ys, ts, ps, bs, D, dt_max, tol, onset=0, last0=None):
    """Per event: look up p0 + d and p0 + 2d in the current SAE, then write SAE[p0] = t0. With ``onset > 0`` only
    events whose pixel's previous event (``last``, every event) is more than ``onset`` older look up and write."""
    sae = sae0.copy()
    last = None if last0 is None else last0.copy()
    B, C, H, W = sae.shape
    out = []
    for i, (x, y, t, p, b) in enumerate(zip(xs, ys, ts, ps, bs)):
        c = int(p) if C == 2 else 0
        if onset:
            silent = int(t) - int(last[b, c, y, x]) > onset
            last[b, c, y, x] = max(last[b, c, y, x], t)
            if not silent:
                continue
        for dy in range(-D, D + 1):
            for dx in range(-D, D + 1):
                if dx == 0 and dy == 0:
                    continue
                x1, y1, x2, y2 = x + dx, y + dy, x + 2 * dx, y + 2 * dy
                t1 = sae[b, c, y1, x1] if 0 <= x1 < W and 0 <= y1 < H else NEVER
                t2 = sae[b, c, y2, x2] if 0 <= x2 < W and 0 <= y2 < H else NEVER
                dt01, dt12 = int(t) - int(t1), int(t1) - int(t2)
                if 0 < dt01 < dt_max and dt12 > 0 and abs(1 - dt12 / dt01) < tol:
                    s = (dt01 + dt12) * 1e-6
                    out.append((i, -2 * dx / s, -2 * dy / s))
        sae[b, c, y, x] = max(sae[b, c, y, x], t)
    return out, sae, last


def edge_events(H, W, normal, speed, t_end_us, offset=0.0, dup=0):
    """A straight edge n . p = offset + speed * t sweeping the sensor; every pixel fires when crossed
    (``dup`` extra events 30 us apart per crossing)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    yy, xx = np.mgrid[0:H, 0:W]
    t = np.round((xx * n[0] + yy * n[1] - offset) / speed * 1e6).astype(np.int64).ravel()
    x, y = xx.ravel(), yy.ravel()
    if dup:
        x, y = np.tile(x, dup + 1), np.tile(y, dup + 1)
        t = np.concatenate([t + 30 * k for k in range(dup + 1)])
    m = (t >= 0) & (t < t_end_us)
    o = np.argsort(t[m], kind="stable")
    return x[m][o], y[m][o], t[m][o]


def ramp_edge_events(H, W, normal, speed, t_end_us, rng, k_max):
    """As :func:`edge_events`, but each crossing fires 1 to ``k_max`` events (random): the first as the edge
    arrives, the others at random times during the crossing (one pixel of travel), as a sensor fires one event per
    contrast threshold."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    yy, xx = np.mgrid[0:H, 0:W]
    k = rng.integers(1, k_max + 1, H * W)
    s = np.repeat((xx * n[0] + yy * n[1]).ravel(), k)
    first = np.concatenate([[True], np.repeat(np.arange(H * W), k)[1:] != np.repeat(np.arange(H * W), k)[:-1]])
    s = s + np.where(first, 0.0, rng.uniform(0, 1, s.size))
    x, y = np.repeat(xx.ravel(), k), np.repeat(yy.ravel(), k)
    t = np.round(s / speed * 1e6).astype(np.int64)
    m = (t >= 0) & (t < t_end_us)
    o = np.argsort(t[m], kind="stable")
    return x[m][o], y[m][o], t[m][o]


def bar_events(H, W, centre, omega, r_min, r_max, t_end_us):
    """A bar through ``centre`` rotating at ``omega`` rad/s (image axes): a pixel at polar angle phi
    fires when the bar's angle (mod pi) reaches it."""
    yy, xx = np.mgrid[0:H, 0:W]
    rx, ry = xx - centre[0], yy - centre[1]
    rho = np.hypot(rx, ry)
    phi = np.mod(np.arctan2(ry, rx), math.pi)
    m = (rho >= r_min) & (rho <= r_max)
    t = np.round(phi[m] / omega * 1e6).astype(np.int64)
    x, y = xx[m], yy[m]
    k = t < t_end_us
    o = np.argsort(t[k], kind="stable")
    return x[k][o], y[k][o], t[k][o]


def add_noise(rng, x, y, t, H, W, frac):
    n = int(frac * len(t) / (1 - frac))
    xn, yn = rng.integers(0, W, n), rng.integers(0, H, n)
    tn = rng.integers(int(t.min()), int(t.max()) + 1, n)
    x, y, t = np.concatenate([x, xn]), np.concatenate([y, yn]), np.concatenate([t, tn])
    o = np.argsort(t, kind="stable")
    return x[o], y[o], t[o]


def run_packets(flow_mod, x, y, t, dt_us, p=None):
    """Feed fixed-duration packets; return the list of FlowFields."""
    out = []
    p = np.ones_like(x) if p is None else p
    edges = np.arange(int(t[0]), int(t[-1]) + dt_us, dt_us)
    idx = np.searchsorted(t, edges)
    for a, b in zip(idx[:-1], idx[1:]):
        out.append(flow_mod(torch.from_numpy(x[a:b]), torch.from_numpy(y[a:b]), torch.from_numpy(t[a:b]),
                            torch.from_numpy(p[a:b]).to(torch.int8)))
    return out


def brute_force_register(flows, events, tie_tol):
    """Evaluate the cost of every candidate with plain loops; near-ties go to the geometric median."""
    ids = sorted(set(events))
    costs = []
    for f in flows:
        c = 0.0
        for i in ids:
            c += min(math.dist(f, g) for g, e in zip(flows, events) if e == i)
        costs.append(c)
    cmin = min(costs)
    near = [k for k, c in enumerate(costs) if c <= cmin + tie_tol * len(ids) * math.hypot(*flows[k])]
    return min(near, key=lambda k: (sum(math.dist(flows[k], g) for g in flows), k)), costs


def register_oracle(flows, events, pixels, tie_tol, inlier):
    """One block registered as the module docstring defines it, in plain float64 arithmetic with every sum taken
    in order (events sorted) and every minimum starting from infinity: the registered flow and uv."""
    F = [(float(u), float(v)) for u, v in flows]
    K = len(F)
    groups = [[j for j in range(K) if events[j] == e] for e in sorted(set(events))]

    def dist(c, j):
        a, b = F[c][0] - F[j][0], F[c][1] - F[j][1]
        return math.sqrt(a * a + b * b)

    cost = []
    for c in range(K):
        s = 0.0
        for g in groups:
            s += min([math.inf] + [dist(c, j) for j in g])
        cost.append(s)
    c_min, best, best_spread = min([math.inf] + cost), 0, math.inf
    for c in range(K):
        if cost[c] <= c_min + tie_tol * len(groups) * math.sqrt(F[c][0] * F[c][0] + F[c][1] * F[c][1]):
            spread = 0.0
            for j in range(K):
                spread += dist(c, j)
            if spread < best_spread:
                best, best_spread = c, spread
    radius = inlier * math.sqrt(F[best][0] * F[best][0] + F[best][1] * F[best][1])
    su = sv = sw = 0.0
    for g in groups:
        if min([math.inf] + [dist(best, j) for j in g]) <= radius:
            for j in g:
                su, sv, sw = su + float(pixels[j][0]), sv + float(pixels[j][1]), sw + 1.0
    return F[best], (su / sw, sv / sw)


# ----------------------------------------------------------------------------------------------- tests
# D = 4: 80 directions, more than one bit mask
@pytest.mark.parametrize("C,B,D,onset", [(1, 1, 2, 0), (2, 2, 2, 0), (1, 1, 4, 0), (1, 1, 2, 60), (2, 2, 2, 60),
                                          (1, 1, 4, 60)])
def test_triplet_samples_match_sequential_oracle(C, B, D, onset):
    rng = np.random.default_rng(3 + C)
    H, W, dt_max, tol = 9, 11, 3000, 0.4
    sae = np.full((B, C, H, W), NEVER, dtype=np.int64)
    last = sae.copy() if onset else None
    t_now = 0
    total = 0
    for n in (300, 0, 500, 400):  # packets; SAE carries over
        x, y = rng.integers(0, W, n), rng.integers(0, H, n)
        x[: n // 4], y[: n // 4] = rng.integers(0, 3, n // 4), rng.integers(0, 3, n // 4)  # repeats in a packet
        b = rng.integers(0, B, n)
        p = rng.integers(0, 2, n)
        t = t_now + np.cumsum(rng.integers(0, 40, n))
        t_now = int(t[-1]) if n else t_now
        ref, sae_next, last_next = triplet_oracle(sae, x, y, t, p, b, D, dt_max, tol, onset, last)
        tx = [torch.from_numpy(a) for a in (x, y, t, p, b)]
        ev, fl = triplet_samples(torch.from_numpy(sae), tx[0].short(), tx[1].short(), tx[2], tx[3].to(torch.int8),
                                 tx[4], D=D, dt_max_us=dt_max, tol=tol, onset_us=onset,
                                 last=None if last is None else torch.from_numpy(last))
        got = sorted(zip(ev.tolist(), fl[:, 0].tolist(), fl[:, 1].tolist()))
        ref = sorted(ref)
        assert len(got) == len(ref)
        for g, r in zip(got, ref):
            assert g[0] == r[0] and g[1] == pytest.approx(r[1], rel=1e-6) and g[2] == pytest.approx(r[2], rel=1e-6)
        if not onset:
            np.testing.assert_array_equal(sae_update(torch.from_numpy(sae), *tx).numpy(), sae_next)
        sae, last = sae_next, last_next
        total += len(ref)
    assert total > 50  # the stream must exercise acceptance, not only rejection


def test_module_keeps_the_onset_state_of_the_oracle():
    """TripletFlow's SAE (onsets) and last-event times after packets equal the sequential oracle's."""
    rng = np.random.default_rng(11)
    B, C, H, W, D, onset = 2, 1, 9, 11, 2, 60
    flow = TripletFlow(H, W, batch_size=B, block=4, min_samples=1, D=D, dt_max_us=3000, tol=0.4, onset_us=onset)
    sae = np.full((B, C, H, W), NEVER, dtype=np.int64)
    last = sae.copy()
    t_now = 0
    for n in (300, 0, 500):
        x, y, b = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, B, n)
        t = t_now + np.cumsum(rng.integers(0, 40, n))
        t_now = int(t[-1]) if n else t_now
        _, sae, last = triplet_oracle(sae, x, y, t, np.zeros(n, int), b, D, 3000, 0.4, onset, last)
        flow(*(torch.from_numpy(a) for a in (x, y, t)), None, torch.from_numpy(b))
        np.testing.assert_array_equal(flow.sae.numpy(), sae)
        np.testing.assert_array_equal(flow.newest.numpy(), last)
    assert (sae != last).any()  # some events were not onsets
    flow.reset(torch.tensor([True, False]))
    assert (flow.last_padded[0] == NEVER).all() and (flow.newest[1].numpy() == last[1]).all()


def test_onsets_read_an_edge_that_fires_several_events_per_crossing():
    """A crossing of 1-4 events (one per contrast threshold): matching every event reads the speed up to several
    percent off; matching the onsets reads it exactly."""
    H, W, speed = 60, 90, 1000.0
    x, y, t = ramp_edge_events(H, W, (1, 0.3), speed, int(80 / speed * 1e6), np.random.default_rng(1), 4)
    truth = torch.tensor([1.0, 0.3]) / math.hypot(1.0, 0.3) * speed
    every = _field_errors(run_packets(TripletFlow(H, W, block=30, min_samples=20, onset_us=0), x, y, t, 2000),
                          lambda uv: truth)
    onsets = _field_errors(run_packets(TripletFlow(H, W, block=30, min_samples=20, onset_us=1000), x, y, t, 2000),
                           lambda uv: truth)
    assert len(onsets) >= 40 and (onsets < 0.01).all(), np.sort(onsets)[-5:]
    assert (every > 0.03).mean() > 0.2, np.sort(every)


def _register(block, events, flows, pixels, n_blocks, **kw):
    return register_blocks(torch.from_numpy(block), torch.from_numpy(events), torch.from_numpy(flows),
                           torch.from_numpy(pixels), n_blocks, **kw)


def test_registration_equals_brute_force():
    rng = np.random.default_rng(0)
    S = 150
    events = np.sort(rng.integers(0, 40, S))
    block = events * 3 // 40  # events 0..39 -> blocks 0..2; an event's samples share its block
    base = np.array([[120.0, -40.0], [0.0, 80.0], [-60.0, -60.0]])[block]
    flows = base + rng.normal(0, 15, (S, 2)) + (rng.random((S, 1)) < 0.2) * rng.normal(0, 200, (S, 2))
    pixels = rng.random((S, 2)) * 30
    for tie_tol in (0.0, 0.05):
        out, uv, valid, count = _register(block, events, flows, pixels, 4, min_samples=5, max_candidates=1000,
                                          tie_tol=tie_tol, estimate="register", inlier=0.25)
        assert count.tolist() == np.bincount(block, minlength=4).tolist()
        assert valid.tolist() == [True, True, True, False]
        for g in range(3):
            m = block == g
            k, _ = brute_force_register(flows[m].tolist(), events[m].tolist(), tie_tol)
            np.testing.assert_allclose(out[g].numpy(), flows[m][k], rtol=1e-6)
            # uv: mean pixel of the samples of events with a candidate within 25 % of |F|
            best = flows[m][k]
            inl = [e for e in set(events[m]) if min(np.linalg.norm(flows[m][events[m] == e] - best, axis=1))
                   <= 0.25 * np.linalg.norm(best)]
            np.testing.assert_allclose(uv[g].numpy(), pixels[m][np.isin(events[m], inl)].mean(0), rtol=1e-5)
        assert out[3].tolist() == [0.0, 0.0] and bool(uv[3].isnan().all())


@pytest.mark.parametrize("kind", ["grid", "float32", "float64", "huge"])
def test_registration_equals_sequential_oracle(kind):
    # Bit for bit, ties included: flows on a coarse grid (many equal costs and spreads: the first candidate
    # wins), float32 flows (as the matching writes them), float64 flows and some huge ones (infinite squared
    # distances); 1..3 samples per event.
    rng = np.random.default_rng({"grid": 0, "float32": 1, "float64": 2, "huge": 3}[kind])
    for tie_tol in (0.0, 0.02, 0.2):
        block, events, flows = [], [], []
        for g in range(12):
            per = rng.integers(1, 4, int(rng.integers(2, 40)))
            n = int(per.sum())
            block += [g] * n
            events += [g * 100 + e for e, k in enumerate(per) for _ in range(k)]
            if kind == "grid":
                flows.append(rng.integers(-3, 4, (n, 2)) * 50.0 + rng.integers(-2, 3, 2) * 100.0)
            else:
                f = rng.normal(0, 300, 2) + rng.normal(0, 40, (n, 2))
                if kind == "huge":
                    f[rng.random(n) < 0.1] *= 1e200
                flows.append(f.astype(np.float32).astype(np.float64) if kind == "float32" else f)
        block, events, flows = np.array(block), np.array(events), np.concatenate(flows)
        pixels = rng.integers(0, 30, (len(block), 2)).astype(np.float64)
        out, uv, valid, _ = _register(block, events, flows, pixels, 12, min_samples=1, max_candidates=1000,
                                      tie_tol=tie_tol, estimate="register", inlier=0.25)
        assert valid.all()
        for g in range(12):
            m = block == g
            f, u = register_oracle(flows[m], events[m], pixels[m], tie_tol, 0.25)
            with np.errstate(over="ignore"):  # a huge flow is infinite in float32, as the output is
                f, u = np.float32(f).tolist(), np.float32(u).tolist()
            assert out[g].tolist() == f and uv[g].tolist() == u, (g, tie_tol)


def test_registration_subsamples_whole_events_when_capped():
    # 60 events x 4 samples; cap 100 -> every 3rd event (20 events, 80 samples) is evaluated.
    events = np.repeat(np.arange(60), 4)
    flows = np.stack([np.arange(240.0), np.zeros(240)], 1)
    out, *_ = _register(np.zeros(240, dtype=np.int64), events, flows, np.zeros((240, 2)), 1, min_samples=1,
                        max_candidates=100, tie_tol=0, estimate="register")
    kept = events % 3 == 0
    k, _ = brute_force_register(flows[kept].tolist(), events[kept].tolist(), 0.0)
    assert out[0].tolist() == flows[kept][k].tolist()



def test_registration_of_unsorted_strided_samples():
    # Samples in any order register as if ordered by (block, event), stably: shuffling whole events (the samples
    # of an event keep their order) leaves the result unchanged, for strided inputs as well.
    rng = np.random.default_rng(2)
    S = 400
    events = np.sort(rng.integers(0, 120, S))
    block = events % 3
    flows = rng.normal(0, 100, (S, 2)) + np.array([[100.0, 0.0], [0.0, 50.0], [-80.0, 30.0]])[block]
    pixels = rng.random((S, 2)) * 30
    kw = dict(min_samples=5, max_candidates=64, tie_tol=0.02, estimate="normal", inlier=0.25)
    ref = _register(block, events, flows, pixels, 3, **kw)
    perm = np.argsort(rng.permutation(120)[events], kind="stable")
    assert (np.diff(events[perm]) < 0).any()
    got = _register(block[perm], events[perm], np.asfortranarray(flows[perm]), pixels[perm][::-1][::-1], 3, **kw)
    assert all(torch.equal(a, b) for a, b in zip(ref, got))


@pytest.mark.parametrize("estimate", ["register", "normal"])
def test_each_block_registers_as_if_alone(estimate):
    # 60 blocks of 5..300 samples (size groups of up to 16/32/64/128 samples after the 128 cap, the
    # largest split into several chunks): every block's result equals registering that block alone.
    rng = np.random.default_rng(5)
    block, events, flows = [], [], []
    for g in range(60):
        n_ev = int(rng.integers(3, 150))
        per = rng.integers(1, 4, n_ev)
        block += [g] * int(per.sum())
        events += [g * 1000 + e for e, k in enumerate(per) for _ in range(k)]
        base = rng.normal(0, 300, 2)
        flows.append(base + rng.normal(0, 30, (int(per.sum()), 2)))
    block, events, flows = np.array(block), np.array(events), np.concatenate(flows)
    pixels = rng.random((len(block), 2)) * 20
    kw = dict(min_samples=5, max_candidates=128, tie_tol=0.02, estimate=estimate, inlier=0.25)
    out, uv, valid, count = _register(block, events, flows, pixels, 60, **kw)
    assert valid.all() and int(count.max()) > 128 and int(count.min()) < 16
    for g in range(60):
        m = block == g
        o, u, _, _ = _register(np.zeros(m.sum(), dtype=np.int64), events[m], flows[m], pixels[m], 1, **kw)
        assert torch.equal(out[g], o[0]) and torch.equal(uv[g], u[0]), g

def test_normal_estimate_recovers_normal_flow_of_an_edge():
    # Candidates of an edge with normal n and speed v: F = v d / (n . d) for offsets with n . d < 0,
    # plus 20 % outlier events; the registration alone is quantised to the offsets' directions.
    rng = np.random.default_rng(1)
    n, v = np.array([np.cos(0.3), np.sin(0.3)]), 250.0
    dirs = [np.array([dx, dy]) for dx in range(-2, 3) for dy in range(-2, 3) if (dx, dy) != (0, 0)]
    flows, events = [], []
    for e in range(40):
        if e % 5 == 4:
            fl = [rng.normal(0, 300, 2) for _ in range(3)]
        else:
            fl = [v * d / (n @ d) * (1 + rng.normal(0, 0.005)) for d in dirs if n @ d < 0]
        flows += fl
        events += [e] * len(fl)
    flows, events = np.array(flows), np.array(events)
    z = np.zeros(len(events), dtype=np.int64)
    reg, *_ = _register(z, events, flows, np.zeros((len(z), 2)), 1, min_samples=5, max_candidates=1000,
                        estimate="register")
    nor, *_ = _register(z, events, flows, np.zeros((len(z), 2)), 1, min_samples=5, max_candidates=1000)
    d_reg = reg[0].double().numpy()
    assert abs(d_reg[0] * n[1] - d_reg[1] * n[0]) / np.linalg.norm(d_reg) > 0.1  # quantised direction
    np.testing.assert_allclose(nor[0].numpy(), n * v, rtol=0.01)


def _field_errors(fields, truth):
    """Relative error |flow - truth(uv)| / |truth(uv)| of every valid block of every field (batch 0)."""
    err = [float((fl.double() - truth(uv.double())).norm() / truth(uv.double()).norm())
           for f in fields for uv, fl in zip(f.uv[0][f.valid[0]], f.flow[0][f.valid[0]])]
    return np.array(err)


def _check_field(fields, truth, rel):
    """Every valid block's flow within rel of truth(uv); returns the number of checked blocks."""
    err = _field_errors(fields, truth)
    assert (err < rel).all(), np.sort(err)[-5:]
    return len(err)


@pytest.mark.parametrize("normal,speed,dup", [((1, 0), 200.0, 0), ((1, 1), 200.0, 0), ((1, 1), 1500.0, 1),
                                              ((-1, 0), 3000.0, 2), ((0, 1), 80.0, 0)])
def test_moving_edge_flow(normal, speed, dup):
    H, W = 60, 90
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    offset = min(0.0, n[0] * (W - 1))  # start at the image border the edge enters from
    x, y, t = edge_events(H, W, normal, speed, int(45 / speed * 1e6), offset=offset, dup=dup)  # 45 px of travel
    m = TripletFlow(H, W, block=30, min_samples=20)
    fields = run_packets(m, x, y, t, 2000)
    truth = torch.tensor(n * speed)
    assert _check_field(fields, lambda uv: truth, 0.05) >= 6


def test_moving_edge_with_noise():
    rng = np.random.default_rng(7)
    H, W = 60, 90
    x, y, t = edge_events(H, W, (1, 1), 400.0, int(60 / 400 * 1e6))
    x, y, t = add_noise(rng, x, y, t, H, W, 0.2)
    fields = run_packets(TripletFlow(H, W, block=30, min_samples=20), x, y, t, 2000)
    truth = torch.tensor([400.0, 400.0]) / math.sqrt(2)
    assert _check_field(fields, lambda uv: truth, 0.10) >= 6


@pytest.mark.parametrize("omega", [20.0, -30.0])
def test_rotating_bar(omega):
    H = W = 120
    c = (59.5, 59.5)
    x, y, t = bar_events(H, W, c, abs(omega), 25, 58, int(math.pi / abs(omega) * 1e6))
    if omega < 0:  # reverse the rotation: mirror the stream in x
        x = W - 1 - x
    m = TripletFlow(H, W, block=20, min_samples=20)
    fields = run_packets(m, x, y, t, 2000)
    # At the start (end) of the half turn the rows next to the horizontal have no history (no future):
    # those triplets see a bar grazing a pixel row. Check the middle 80 %.
    fields = fields[len(fields) // 10: len(fields) * 9 // 10]

    def truth(uv):  # omega x r in image axes
        return omega * torch.stack([-(uv[1] - c[1]), uv[0] - c[0]])

    err = _field_errors(fields, truth)
    # One vector per 20 px block of a field that varies by up to +-40 % across it (inner blocks), from as
    # few as 20 samples: most within 5 %, all within 10 %.
    assert len(err) >= 30 and np.mean(err < 0.05) >= 0.95 and err.max() < 0.10 and np.median(err) < 0.03, err


def test_per_polarity_channels_do_not_mix():
    H, W = 30, 60
    x, y, t = edge_events(H, W, (1, 0), 500.0, 100_000)
    p = (x % 2).astype(np.int8)  # alternate polarity per column: no same-polarity triplet at d = +-1
    both = run_packets(TripletFlow(H, W, block=30, min_samples=5), x, y, t, 2000, p)
    split = run_packets(TripletFlow(H, W, block=30, min_samples=5, per_polarity=True), x, y, t, 2000, p)
    assert sum(int(f.count.sum()) for f in split) < sum(int(f.count.sum()) for f in both)
    n = _check_field(split, lambda uv: torch.tensor([500.0, 0.0]), 0.05)
    assert n > 0


def test_field_layout_and_uv():
    gy, gx, centres = block_grid(50, 70, 30)
    assert (gy, gx) == (2, 3)
    assert centres.tolist()[0] == [14.5, 14.5] and centres.tolist()[2] == [64.5, 14.5]
    assert centres.tolist()[5] == [64.5, 39.5]
    m = TripletFlow(50, 70, batch_size=2, block=30)
    f = m(torch.tensor([1, 2, 3]), torch.tensor([1, 1, 1]), torch.tensor([0, 1, 2]), torch.tensor([1, 1, 1]),
          torch.tensor([0, 1, 1]))
    assert f.uv.shape == (2, 6, 2) and f.flow.shape == (2, 6, 2) and f.valid.shape == (2, 6)
    assert not f.valid.any() and torch.equal(f.uv[0], centres) and int(f.count.sum()) == 0
    assert m.sae[1, 0, 1, 3] == 2 and m.sae[0, 0, 1, 1] == 0 and m.sae[0, 0, 1, 2] == NEVER
    m.reset()
    assert bool((m.sae == NEVER).all())


def test_bad_inputs():
    with pytest.raises(ValueError, match="D"):
        TripletFlow(10, 10, D=0)
    with pytest.raises(ValueError, match="block"):
        TripletFlow(10, 10, block=0)
    m = TripletFlow(10, 10)
    with pytest.raises(TypeError, match="int64"):
        m(torch.tensor([1]), torch.tensor([1]), torch.tensor([1.0]), torch.tensor([1]))
    with pytest.raises(ValueError, match="y must lie"):
        m(torch.tensor([1]), torch.tensor([10]), torch.tensor([1]), torch.tensor([1]))
    with pytest.raises(ValueError, match="sae"):
        triplet_samples(torch.zeros(1, 1, 5, 5), torch.tensor([1]), torch.tensor([1]), torch.tensor([1]), None)
    with pytest.raises(ValueError, match="onset_us"):
        TripletFlow(10, 10, onset_us=-1)
    sae = torch.full((1, 1, 5, 5), NEVER, dtype=torch.int64)
    with pytest.raises(ValueError, match="needs last"):
        triplet_samples(sae, torch.tensor([1]), torch.tensor([1]), torch.tensor([1]), None, onset_us=10)


def test_rows_update_only_their_elements_as_the_whole_batch_would():
    """forward(..., rows=) on a share of the batch (b counted from its start) gives that share's flow field and
    SAE rows exactly as the whole-batch call, and leaves the other rows alone (threads update disjoint rows)."""
    B, H, W = 3, 60, 90
    edges = [edge_events(H, W, n, 400.0, 20_000) for n in ((1, 0), (0, 1), (1, 1))]  # one edge per element
    x, y, t = (torch.from_numpy(np.concatenate([e[i] for e in edges])).long() for i in range(3))
    b = torch.cat([torch.full((len(e[0]),), i) for i, e in enumerate(edges)])
    p = torch.zeros_like(x)
    whole, part = (TripletFlow(H, W, batch_size=B, block=30, min_samples=20) for _ in range(2))
    vectors = 0
    for k in range(0, 20_000, 2000):  # ten packets, so later ones match against the history
        sel = (t >= k) & (t < k + 2000)
        ref = whole(x[sel], y[sel], t[sel], p[sel], b[sel])
        mine = sel & (b >= 1)
        out = part(x[mine], y[mine], t[mine], p[mine], b[mine] - 1, rows=slice(1, 3))
        for got, want in zip(out, ref):
            assert torch.equal(torch.nan_to_num(got), torch.nan_to_num(want[1:]))
        vectors += int(out.valid.sum())
    assert vectors > 0 and torch.equal(part.sae[1:], whole.sae[1:]) and (part.sae[0] == NEVER).all()
