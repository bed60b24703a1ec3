import math

import pytest
import torch

from torchevtrack.synth.esim import ESIM, LOG_EPS, esim_step

NEVER = -(1 << 62)


def one(v):
    return torch.tensor([[v]], dtype=torch.float64)


def step1(L0, L1, ref, C, t0=0, t1=1000, last=NEVER, refr=0):
    return esim_step(one(L0), one(L1), t0, t1, one(ref), one(C), torch.tensor([[last]]), refr)


def test_up_ramp_exact_times_and_polarity():
    # levels 0.25, 0.5, 0.75, 1.0 on the ramp 0 -> 1 over 1000 us: crossed at 250, 500, 750, 1000 us
    x, y, t, p, ref, last = step1(0.0, 1.0, 0.0, 0.25)
    assert t.tolist() == [250, 500, 750, 1000]
    assert p.tolist() == [1, 1, 1, 1] and x.tolist() == [0] * 4 and y.tolist() == [0] * 4
    assert ref.item() == 1.0 and last.item() == 1000


def test_down_ramp_and_lagging_reference():
    x, y, t, p, ref, _ = step1(0.0, -1.0, 0.0, 0.25, t0=2000, t1=4000)
    assert t.tolist() == [2500, 3000, 3500, 4000] and p.tolist() == [0] * 4
    # ref above L0: the first level is ref + C = 0.375, floor(0.875 / 0.25) = 3 events
    _, _, t, p, ref, _ = step1(0.0, 1.0, 0.125, 0.25)
    assert t.tolist() == [375, 625, 875] and p.tolist() == [1, 1, 1] and ref.item() == 0.875


def test_constant_level_one_threshold_from_ref():
    # ref exactly C below a constant level: one event, at t0 (no division by zero)
    x, y, t, p, ref, _ = step1(0.25, 0.25, 0.0, 0.25, t0=100, t1=200)
    assert t.tolist() == [100] and p.tolist() == [1] and ref.item() == 0.25


def test_count_is_floor_delta_over_C():
    for L1 in (0.1, 0.3, 0.59, 0.61, 2.05):
        _, _, t, _, ref, _ = step1(0.0, L1, 0.0, 0.2)
        assert len(t) == math.floor(L1 / 0.2)
        assert abs(ref.item() - 0.2 * math.floor(L1 / 0.2)) < 1e-12


def test_refractory_drops_events_but_advances_ref():
    _, _, t, p, ref, last = step1(0.0, 1.0, 0.0, 0.25, refr=300)
    assert t.tolist() == [250, 750]  # 500 and 1000 are within 300 us of the previous emitted event
    assert ref.item() == 1.0 and last.item() == 750
    # next interval continues from ref = 1.0 (not from the last emitted level)
    _, _, t, _, ref, last = esim_step(one(1.0), one(1.5), 1000, 2000, ref, one(0.25), last, 300)
    assert t.tolist() == [1500, 2000] and ref.item() == 1.5


def reference_esim(frames, times, C, refr):
    """Obviously-correct per-pixel sequential ESIM on Python floats."""
    H, W = len(frames[0]), len(frames[0][0])
    ref = [[frames[0][i][j] for j in range(W)] for i in range(H)]
    last = [[NEVER] * W for _ in range(H)]
    events = []
    for f in range(1, len(frames)):
        L0, L1, t0, t1 = frames[f - 1], frames[f], times[f - 1], times[f]
        for i in range(H):
            for j in range(W):
                d = L1[i][j] - ref[i][j]
                n = math.floor(abs(d) / C[i][j])
                pol = 1.0 if d > 0 else -1.0
                for k in range(1, n + 1):
                    level = ref[i][j] + pol * k * C[i][j]
                    span = L1[i][j] - L0[i][j]
                    tau = min(max((level - L0[i][j]) / span, 0.0), 1.0) if span != 0 else 0.0
                    te = t0 + math.floor(tau * (t1 - t0))
                    if te - last[i][j] >= refr:
                        events.append((te, i * W + j, k, j, i, int(pol > 0)))
                        last[i][j] = te
                ref[i][j] = ref[i][j] + pol * n * C[i][j]
    events.sort(key=lambda e: e[:3])
    return [(e[3], e[4], e[0], e[5]) for e in events]


@pytest.mark.parametrize("refr", [0, 150])
def test_matches_sequential_reference_on_random_frames(refr):
    g = torch.Generator().manual_seed(3)
    H, W, n = 6, 5, 12
    images = torch.rand(n, H, W, generator=g, dtype=torch.float64)
    times = torch.cumsum(torch.randint(50, 900, (n,), generator=g), 0) - 40
    sim = ESIM(H, W, C=0.2, sigma_C=0.05, refractory_us=refr, seed=7)
    got = []
    for img, t in zip(images, times.tolist()):
        ev = sim(img, t)
        got += list(zip(ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist()))
    logs = torch.log(images + LOG_EPS).tolist()
    expected = reference_esim(logs, times.tolist(), sim.C.tolist(), refr)
    assert len(expected) > 50
    assert got == expected


def test_threshold_map_statistics_and_clipping():
    sim = ESIM(100, 100, C=0.2, sigma_C=0.03, seed=1)
    assert abs(sim.C.mean().item() - 0.2) < 0.002 and abs(sim.C.std().item() - 0.03) < 0.002
    assert ESIM(50, 50, C=0.05, sigma_C=0.1, seed=1).C.min().item() == 0.01


def test_roi_step_equals_full_frame_step():
    g = torch.Generator().manual_seed(0)
    a = torch.full((12, 16), 0.3, dtype=torch.float64)
    frames = [a.clone() for _ in range(4)]
    for k, f in enumerate(frames[1:], 1):
        f[3:8, 4 + k: 9 + k] = torch.rand(5, 5, generator=g, dtype=torch.float64)
    full, part = ESIM(12, 16, seed=2), ESIM(12, 16, seed=2)
    full(frames[0], 0)
    part(frames[0], 0)
    for k in range(1, 4):
        e1 = full(frames[k], 100 * k)
        roi = (3, 2, 12, 7)
        e2 = part(frames[k][2:9, 3:15], 100 * k, roi=roi)
        assert len(e1) > 0
        for f in ("x", "y", "t", "p"):
            assert torch.equal(getattr(e1, f), getattr(e2, f))
    assert torch.equal(full.ref, part.ref)


def test_noise_rate_and_reference_untouched():
    sim = ESIM(20, 30, noise_rate_hz=50.0, seed=4)
    img = torch.full((20, 30), 0.5)
    sim(img, 0)
    ref0 = sim.ref.clone()
    ev = sim(img, 200_000)  # expected 50 * 600 * 0.2 = 6000 noise events
    assert abs(len(ev) - 6000) < 4 * math.sqrt(6000)
    assert bool((ev.t[1:] >= ev.t[:-1]).all()) and int(ev.t.min()) >= 0 and int(ev.t.max()) < 200_000
    assert torch.equal(sim.ref, ref0)
    assert 0.45 < ev.p.double().mean().item() < 0.55


def test_bad_input():
    sim = ESIM(4, 4)
    with pytest.raises(ValueError, match="shape"):
        sim(torch.zeros(3, 4), 0)
    sim(torch.zeros(4, 4), 10)
    with pytest.raises(ValueError, match="increasing"):
        sim(torch.zeros(4, 4), 10)
    with pytest.raises(ValueError, match="t1"):
        step1(0.0, 1.0, 0.0, 0.25, t0=5, t1=5)
