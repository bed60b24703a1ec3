"""bind_observe against its oracle: the EROS stage, the time surface stage and canvas_observation, bit for bit."""

import torch

from torchevtrack.stages.eros import EROS, TimeSurface, bind_observe, canvas_observation, recency_arrays

H, W, B = 60, 80, 2
MAX_AGE_US = 30_000
RECENCY_US = torch.tensor([4_000.0, 1_500.0])  # one window per element
RECENCY = recency_arrays(RECENCY_US, B, MAX_AGE_US)


def _window(seed, t0, n=2500):
    """Events along a moving edge and noise, packed by element (time order within each)."""
    gen = torch.Generator().manual_seed(seed)
    b = torch.randint(0, B, (n,), generator=gen).sort().values
    t = t0 + torch.randint(0, 2000, (n,), generator=gen)
    x = ((t - t0) // 100 + 20 + torch.randint(0, 3, (n,), generator=gen)).clamp(0, W - 1)
    y = torch.randint(0, H, (n,), generator=gen)
    order = torch.argsort(b * 10_000_000 + t)
    return x[order].int(), y[order].short(), t[order], b


def _numpy(*v):
    return tuple(None if a is None else a.numpy() for a in v)


def test_observe_is_the_stages_then_the_observation_bit_for_bit():
    eros, times, ref_eros, ref_times = EROS(H, W, batch_size=B), TimeSurface(H, W, B), EROS(H, W, batch_size=B), \
        TimeSurface(H, W, B)
    box = torch.tensor([[40.0, 30.0, 50.0], [35.5, 28.0, 90.0]], dtype=torch.float64)  # the second beyond the frame
    run = bind_observe(eros, times, RECENCY, canvas=32, max_age_us=MAX_AGE_US)
    for k in range(3):  # later windows see the surfaces the earlier ones left, and older events weigh less
        x, y, t, b = _window(k, 10_000 + 2000 * k)
        t_now = torch.stack([t[b == i].max() for i in range(B)])
        got = torch.from_numpy(run(*_numpy(x, y, t, b, box, t_now)))
        ref_eros(x, y, b)
        ref_times(x, y, t, b)
        want = canvas_observation(ref_eros.surface, ref_times.last_us[:, None], box, 32, t_now, MAX_AGE_US, RECENCY_US)
        assert got.dtype == want.dtype and torch.equal(got, want)
        assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(times.last_us, ref_times.last_us)
    assert float(want.max()) > 0 and float(want.min()) == 0  # edges observed, and the empty part


def test_one_element_and_no_box():
    eros, times, ref_eros, ref_times = EROS(H, W), TimeSurface(H, W), EROS(H, W), TimeSurface(H, W)
    x, y, t, b = _window(5, 0)
    keep = b == 1
    x, y, t = x[keep], y[keep], t[keep]
    assert bind_observe(eros, times, recency_arrays(0.0, 1, 0), canvas=32)(
        *_numpy(x, y, t, None, None, t.max()[None])) is None
    ref_eros(x, y)
    ref_times(x, y, t)
    assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(times.last_us, ref_times.last_us)
    assert float(eros.surface.max()) == 1


def test_events_outside_the_surfaces_write_nothing():
    eros, times = EROS(H, W, batch_size=B), TimeSurface(H, W, B)
    x, y, t, b = _window(6, 0)
    t_now = torch.zeros(B, dtype=torch.long)
    run = bind_observe(eros, times, recency_arrays(0.0, B, 0), canvas=32)
    box = torch.tensor([[40.0, 30.0, 50.0]] * B, dtype=torch.float64)
    assert run(*_numpy(x.clone().fill_(W), y, t, b, box, t_now)) is False
    assert run(*_numpy(x, y, t, b.clone().fill_(B), None, t_now)) is False
    assert float(eros.surface.abs().max()) == 0 and bool((times.last_us == times.last_us.min()).all())
