"""The burst guard against a sequential scalar oracle and a vectorised numpy reference of the rule, and its
behaviour on flashes and rate changes; its numpy views of the buffers follow copies, pickles and new buffers."""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest
import torch

from torchevtrack.stages.burst import BurstGuard, burst_update_, keep_events


def oracle(counts, dt_us, floor, ratio, ema, max_run):
    """Scalar reference for one element: window counts -> burst flags."""
    rate, run, out = None, 0, []
    for n in counts:
        burst = rate is not None and n > floor and n > ratio * rate * dt_us * 1e-6 and run < max_run
        if not burst:
            r = n / (dt_us * 1e-6)
            if rate is None or run >= max_run:
                rate = r if n > 0 else None  # the first window with events starts the rate
            else:
                rate = (1 - ema) * rate + ema * r
        run = run + 1 if burst else 0
        out.append(burst)
    return out


def reference_step(n, dt_us, rate, run, floor, ratio, ema, max_run):
    """The rule for ``B`` elements in numpy, one window: ``(B,)`` counts and state -> flags, rate, run (new arrays)."""
    n = np.asarray(n).astype(np.float64)
    dt = dt_us * 1e-6
    fresh = np.isnan(rate)
    burst = ~fresh & (n > floor) & (n > ratio * np.where(fresh, 0.0, rate) * dt) & (run < max_run)
    restart = fresh | (run >= max_run)
    new_rate = np.where(restart, np.where(n > 0, n / dt, np.nan), (1 - ema) * np.where(fresh, 0.0, rate) + ema * n / dt)
    return burst, np.where(burst, rate, new_rate), np.where(burst, run + 1, 0).astype(np.int64)


def reference_keep(b, n, burst):
    """Event by event: keep an event unless its element's window is a burst (``b`` None: all in element 0)."""
    return np.array([not burst[0 if b is None else int(b[i])] for i in range(n)], dtype=bool)


def kept(b, n, burst):
    """:func:`keep_events` as the ``(n,)`` bool mask it selects."""
    k = keep_events(b, n, torch.as_tensor(burst))
    if isinstance(k, slice):
        mask = np.zeros(n, dtype=bool)
        mask[k] = True
        return mask
    return k.numpy()


def packed_batch(counts, gen):
    """Batch indices ``(N,)`` of a packed window holding ``counts[k]`` events of element k, in random order."""
    b = torch.repeat_interleave(torch.arange(len(counts)), torch.as_tensor(counts))
    return b[torch.randperm(len(b), generator=gen)]


@pytest.mark.parametrize("B", [1, 2, 5])
def test_matches_the_numpy_reference_on_random_windows(B):
    gen = torch.Generator().manual_seed(B)
    H, W, T = 60, 80, 300
    floor, ratio, ema, max_run = 0.05 * H * W, 6.0, 0.07, 8
    g = BurstGuard(H, W, min_fraction=0.05, ratio=ratio, ema=ema, max_run=max_run, batch_size=B)
    rate, run = np.full(B, np.nan), np.zeros(B, dtype=np.int64)
    scale = torch.exp(torch.empty(T, B).uniform_(0, 8, generator=gen))  # 1 to 3000 events, all scales of rate
    counts = (scale * torch.rand(T, B, generator=gen)).long()
    counts[torch.rand(T, B, generator=gen) < 0.08] += 2_000  # flashes
    counts[100:130, 0] = 1_500  # a lasting change longer than max_run
    n_bursts = 0
    for i in range(T):
        dt_us = int(torch.randint(500, 5000, (1,), generator=gen))
        if i == 150:
            g.reset(torch.tensor([B - 1]))
            rate[B - 1], run[B - 1] = np.nan, 0
        want, rate, run = reference_step(counts[i].numpy(), dt_us, rate, run, floor, ratio, ema, max_run)
        got = g(counts[i], dt_us)
        assert got.numpy().tolist() == want.tolist(), i
        assert np.array_equal(g.rate.numpy(), rate, equal_nan=True) and np.array_equal(g.run.numpy(), run), i
        assert torch.equal(g.burst, got)
        if i % 10 == 0 or want.any():
            b = None if B == 1 else packed_batch(counts[i].tolist(), gen)
            n = int(counts[i].sum())
            assert np.array_equal(kept(b, n, got), reference_keep(b, n, want)), i
        n_bursts += int(want.sum())
    assert n_bursts > 10


def test_a_flash_in_one_element_drops_its_events_only():
    gen = torch.Generator().manual_seed(7)
    H, W, B = 120, 160, 3
    g = BurstGuard(H, W, batch_size=B)
    rate, run = np.full(B, np.nan), np.zeros(B, dtype=np.int64)
    windows = [torch.randint(300, 600, (B,), generator=gen) for _ in range(40)]
    for i in (30, 31):  # every pixel of element 1 fires 4 times, over two 2 ms windows
        windows[i][1] += 2 * H * W
    flags = []
    for c in windows:
        want, rate, run = reference_step(c.numpy(), 2000, rate, run, 0.05 * H * W, 10.0, 0.05, 25)
        got = g(c, 2000)
        b = packed_batch(c.tolist(), gen)
        keep = kept(b, len(b), got)
        assert got.tolist() == want.tolist()
        assert np.array_equal(keep, reference_keep(b, len(b), want))
        assert int(keep.sum()) == int(c[~got].sum())
        flags.append(got)
    flags = torch.stack(flags)
    assert flags.nonzero().tolist() == [[30, 1], [31, 1]]


def test_functional_step_inputs_and_checks():
    g = BurstGuard(10, 10, batch_size=2, ratio=3.0)
    rate, run, burst = g.rate.clone(), g.run.clone(), g.burst.clone()
    flags = []
    for c in ([3, 4], np.array([3, 400], dtype=np.int32), torch.tensor([2, 9], dtype=torch.int16)):
        burst_update_(rate, run, burst, c, 1000, floor=g.floor, ratio=g.ratio, ema=g.ema, max_run=g.max_run)
        assert torch.equal(g(c, 1000), burst)
        assert torch.equal(g.rate, rate) and torch.equal(g.run, run)
        flags.append(burst.tolist())
    assert flags == [[False, False], [False, True], [False, False]]  # floor 5 events; 400 > 3 x 4 events
    with pytest.raises(ValueError, match="float64"):
        burst_update_(rate.float(), run, burst, [1, 2], 1000, floor=5.0, ratio=3.0, ema=0.1, max_run=3)
    with pytest.raises(ValueError, match="integer"):
        g([True, False], 1000)
    with pytest.raises(ValueError, match="integer"):
        g(torch.tensor([1, 2, 3]), 1000)
    assert torch.equal(g.rate, rate)  # nothing written by a refused call


def test_the_guards_arrays_follow_copies_pickles_and_new_buffers():
    g = BurstGuard(10, 10, batch_size=2, ratio=3.0)
    g([4, 4], 1000)  # at most the floor (5 events): accepted, the rate starts at 4 events per window
    twin = copy.deepcopy(g)
    thawed = pickle.loads(pickle.dumps(g))
    assert g([400, 4], 1000).tolist() == [True, False]  # the copies share no state with g
    for other in (twin, thawed):
        assert other.run.tolist() == [0, 0]
        assert other([4, 400], 1000).tolist() == [False, True] and other.run.tolist() == [0, 1]
    assert g.run.tolist() == [1, 0]
    g.load_state_dict(twin.state_dict())
    assert g.run.tolist() == [0, 1] and g([4, 400], 1000).tolist() == [False, True] and g.run.tolist() == [0, 2]
    g.run = torch.zeros(2, dtype=torch.int64)  # a new buffer tensor
    g.rate = torch.full((2,), 4000.0, dtype=torch.float64)  # 4 events per 1 ms window
    assert g([400, 400], 1000).tolist() == [True, True] and g.run.tolist() == [1, 1]
    g.float()
    with pytest.raises(ValueError, match="float64"):
        g([1, 2], 1000)


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


def test_a_dense_start_is_the_scene_not_a_burst():
    """With no history nothing is far above normal: the first window with events starts the rate, however dense
    (a 640x480 scene at 9.6 M events/s lost its first 30 ms when the first windows were judged bursts); empty
    windows before it leave it unset, and a reset starts over."""
    g = BurstGuard(100, 100)  # floor 500 events
    counts = [0, 0, 5_000, 5_000, 5_000, 60_000, 5_000]
    flags = [bool(g(torch.tensor([n]), 2000)) for n in counts]
    assert flags == [False, False, False, False, False, True, False]
    assert flags == oracle(counts, 2000, 500.0, 10.0, 0.05, 25)
    assert math.isclose(float(g.rate[0]), 2.5e6)
    g.reset()
    assert not bool(g(torch.tensor([60_000]), 2000)) and math.isclose(float(g.rate[0]), 3e7)


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
