"""The burst guard against a sequential scalar oracle, and its behaviour on flashes and rate changes."""

from __future__ import annotations

import math

import pytest
import torch

from torchevtrack.stages.burst import BurstGuard, keep_events


def oracle(counts, dt_us, floor, ratio, ema, max_run):
    """Scalar reference for one element: window counts -> burst flags."""
    rate, run, out = None, 0, []
    for n in counts:
        above = rate is None or n > ratio * rate * dt_us * 1e-6
        burst = n > floor and above and run < max_run
        if not burst:
            r = n / (dt_us * 1e-6)
            rate = r if rate is None or run >= max_run else (1 - ema) * rate + ema * r
        run = run + 1 if burst else 0
        out.append(burst)
    return out


def test_matches_oracle_batched():
    gen = torch.Generator().manual_seed(0)
    B, T, H, W = 3, 400, 100, 120
    counts = torch.randint(0, 400, (T, B), generator=gen)
    counts[torch.rand(T, B, generator=gen) < 0.05] = 20_000  # flashes
    counts[200:240, 1] = 9_000  # a lasting change of scene in element 1
    g = BurstGuard(H, W, min_fraction=0.05, ratio=8.0, ema=0.1, max_run=10, batch_size=B)
    got = torch.stack([g(c, 1000) for c in counts])
    for k in range(B):
        want = oracle(counts[:, k].tolist(), 1000, 0.05 * H * W, 8.0, 0.1, 10)
        assert got[:, k].tolist() == want
    assert got[200:210, 1].all() and not got[215:240, 1].any()  # accepted after max_run, then the new normal
    assert got.sum() > 10


def test_flash_detected_fast_motion_not():
    g = BurstGuard(720, 1280)
    fast = [12_000] * 50  # 6 M events/s in 2 ms windows: fast motion with noise at 1280x720
    flags = [bool(g(torch.tensor([n]), 2000)) for n in [500] * 20 + fast + [2_500_000, 1_500_000] + fast]
    assert flags[70:72] == [True, True] and sum(flags) == 2
    assert math.isclose(float(g.rate[0]), 6e6, rel_tol=0.01)


def test_keep_events_and_reset():
    burst = torch.tensor([False, True])
    assert keep_events(None, 7, torch.tensor([True])) == slice(0, 0)
    assert keep_events(None, 7, torch.tensor([False])) == slice(0, 7)
    assert keep_events(torch.tensor([0, 1, 1, 0]), 4, burst).tolist() == [True, False, False, True]
    g = BurstGuard(10, 10, batch_size=2)
    g(torch.tensor([3, 4]), 1000)
    g.reset(torch.tensor([1]))
    assert not math.isnan(float(g.rate[0])) and math.isnan(float(g.rate[1]))
    with pytest.raises(ValueError, match="integer"):
        g(torch.tensor([1.0, 2.0]), 1000)
    with pytest.raises(ValueError, match="dt_us"):
        g(torch.tensor([1, 2]), 0)
