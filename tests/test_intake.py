"""bind_intake against its oracle: the EROS stage, the time surface stage and then the flow stage, bit for bit."""

import pytest
import torch

from torchevtrack.stages.eros import EROS, TimeSurface
from torchevtrack.stages.flow import FlowField, TripletFlow
from torchevtrack.update import bind_intake

H, W, B = 60, 80, 3


def _stages(B=B, onset_us=1000):
    """Two polarity channels: the flow checks the polarities too."""
    return EROS(H, W, batch_size=B), TimeSurface(H, W, batch_size=B), \
        TripletFlow(H, W, batch_size=B, block=20, min_samples=5, per_polarity=True, onset_us=onset_us)


def intake(eros, times, flow, x, y, t, p=None, b=None, rows=None):
    """The tracker's call: the bound intake, its numpy flow field as tensors."""
    return FlowField(*(torch.from_numpy(a) for a in bind_intake(eros, times, flow, rows)(x, y, t, p, b)))


def _window(seed, t0, n=3000, B=B):
    """Events of edges sweeping each element at its own speed, with noise, packed by element."""
    gen = torch.Generator().manual_seed(seed)
    b = torch.randint(0, B, (n,), generator=gen).sort().values
    t = t0 + torch.randint(0, 2000, (n,), generator=gen)
    speed = 0.01 + 0.01 * b  # px / us
    x = ((t - t0) * speed + torch.randint(0, 3, (n,), generator=gen) + 10).long().clamp(0, W - 1)
    y = torch.randint(0, H, (n,), generator=gen)
    order = torch.argsort(b * 10_000_000 + t)
    p = torch.randint(0, 2, (n,), generator=gen)
    return x[order].int(), y[order].short(), t[order], p[order], b


@pytest.mark.parametrize("onset_us", [0, 1000])
def test_intake_is_the_eros_then_the_flow_bit_for_bit(onset_us):
    eros, times, flow = _stages(onset_us=onset_us)
    ref_eros, ref_times, ref_flow = _stages(onset_us=onset_us)
    for k in range(3):  # later windows see the surfaces the earlier ones left
        x, y, t, p, b = _window(k, 10_000 + 2000 * k)
        got = intake(eros, times, flow, x, y, t, p, b)
        ref_eros(x, y, b)
        ref_times(x, y, t, b)
        want = ref_flow(x, y, t, p, b)
        for a, c in zip(got, want):
            assert a.dtype == c.dtype and torch.equal(a, c)
        assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(flow.sae_padded, ref_flow.sae_padded)
        assert torch.equal(flow.last_padded, ref_flow.last_padded)
        assert torch.equal(times.last_us, ref_times.last_us)
    assert int(want.valid.sum()) > 0 and float(eros.surface.max()) > 0  # the comparison covers real work
    # the time surface holds the flow's newest event times, either polarity: the observation may read either
    assert torch.equal(times.last_us, flow.newest.amax(1))
    assert torch.equal(flow.newest, flow.sae) == (onset_us == 0)  # with onsets, some events were not matched


def test_rows_and_one_element_without_a_batch_index():
    eros, times, flow = _stages()
    ref_eros, ref_times, ref_flow = _stages()
    x, y, t, p, b = _window(1, 5000)
    keep = b == 1
    got = intake(eros, times, flow, x[keep], y[keep], t[keep], p[keep], b[keep] - 1, rows=slice(1, 2))
    ref_eros(x[keep], y[keep], b[keep] - 1, rows=slice(1, 2))
    ref_times(x[keep], y[keep], t[keep], b[keep] - 1, rows=slice(1, 2))
    want = ref_flow(x[keep], y[keep], t[keep], p[keep], b[keep] - 1, rows=slice(1, 2))
    assert all(torch.equal(a, c) for a, c in zip(got, want))
    assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(flow.sae_padded, ref_flow.sae_padded)
    assert torch.equal(times.last_us, ref_times.last_us)
    one_eros, one_times, one_flow = _stages(B=1)
    ref_eros, ref_times, ref_flow = _stages(B=1)
    got = intake(one_eros, one_times, one_flow, x[keep], y[keep], t[keep], p[keep])
    ref_eros(x[keep], y[keep])
    ref_times(x[keep], y[keep], t[keep])
    want = ref_flow(x[keep], y[keep], t[keep], p[keep])
    assert all(torch.equal(a, c) for a, c in zip(got, want))
    assert torch.equal(one_eros.surface, ref_eros.surface) and torch.equal(one_times.last_us, ref_times.last_us)


def test_bad_events_raise_the_stages_errors_and_write_nothing():
    eros, times, flow = _stages()
    x, y, t, p, b = _window(2, 5000)
    before = eros.surface.clone(), times.last_us.clone(), flow.sae_padded.clone()
    for bad, match in (((x.clone().fill_(W), y, t, p, b), "x"), ((x, y, t, p.clone().fill_(2), b), "p must"),
                       ((x, y, t, p, b.clone().fill_(B)), "b")):
        with pytest.raises(ValueError, match=match):
            intake(eros, times, flow, *bad)
        assert torch.equal(eros.surface, before[0]) and torch.equal(times.last_us, before[1])
        assert torch.equal(flow.sae_padded, before[2])
    with pytest.raises(TypeError):
        intake(eros, times, flow, x.float(), y, t, p, b)
    with pytest.raises(ValueError, match="same elements"):
        intake(EROS(H, W, batch_size=2), times, flow, x, y, t, p, b)


def test_the_flow_alone_and_the_checked_events():
    """surfaces=False leaves the EROS and the time surface alone; checked sees the events once they are known to be in
    range, and bad events raise before it is called."""
    eros, times, flow = _stages()
    ref_eros, ref_times, ref_flow = _stages()
    x, y, t, p, b = _window(3, 7000)
    seen = []
    got = bind_intake(eros, times, flow)(x, y, t, p, b, surfaces=False, checked=lambda *ev: seen.append(ev))
    want = ref_flow(x, y, t, p, b)
    assert all(torch.equal(torch.from_numpy(a), c) for a, c in zip(got, want))
    assert torch.equal(flow.sae_padded, ref_flow.sae_padded)
    assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(times.last_us, ref_times.last_us)  # untouched
    (xs, ys, ts, bs), = seen
    assert (xs == x.numpy()).all() and (ys == y.numpy()).all() and (ts == t.numpy()).all() and (bs == b.numpy()).all()
    seen.clear()
    with pytest.raises(ValueError, match="p must"):
        bind_intake(eros, times, flow)(x, y, t, p.clone().fill_(2), b, surfaces=False, checked=seen.append)
    assert not seen and torch.equal(flow.sae_padded, ref_flow.sae_padded)


def test_without_a_time_surface():
    """time_surface None: the EROS and the flow alone, as their stage calls."""
    eros, _, flow = _stages()
    ref_eros, _, ref_flow = _stages()
    x, y, t, p, b = _window(4, 9000)
    got = intake(eros, None, flow, x, y, t, p, b)
    ref_eros(x, y, b)
    want = ref_flow(x, y, t, p, b)
    assert all(torch.equal(a, c) for a, c in zip(got, want))
    assert torch.equal(eros.surface, ref_eros.surface) and torch.equal(flow.sae_padded, ref_flow.sae_padded)
