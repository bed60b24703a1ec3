"""The background-activity / hot-pixel filter against a sequential pure-Python oracle, and its behaviour."""

from __future__ import annotations

import pytest
import torch

from torchevtrack.stages.denoise import BackgroundActivityFilter, denoise_update_

NEVER = None


def oracle(events, H, W, dt, period, ratio, min_count):
    """Obviously-correct reference: events ``[(b, x, y, t)]`` in time order per element -> keep flags."""
    last, count, hot, end = {}, {}, {}, {}
    keep = []
    for b, x, y, t in events:
        if b not in end:
            end[b] = t + period
        elif t >= end[b]:
            new_hot = set()
            for (bb, u, v), n in count.items():
                if bb != b or n < min_count:
                    continue
                nb = [(uu, vv) for uu in (u - 1, u, u + 1) for vv in (v - 1, v, v + 1)
                      if (uu, vv) != (u, v) and 0 <= uu < W and 0 <= vv < H]
                m = sum(count.get((b, uu, vv), 0) for uu, vv in nb) / len(nb)
                if n > ratio * max(m, 1.0):
                    new_hot.add((u, v))
            hot[b] = new_hot
            count = {k: n for k, n in count.items() if k[0] != b}
            while t >= end[b]:
                end[b] += period
        count[(b, x, y)] = count.get((b, x, y), 0) + 1
        if (x, y) in hot.get(b, set()):
            keep.append(False)
            continue
        ok = any(0 <= x + du < W and 0 <= y + dv < H and (du, dv) != (0, 0)
                 and (b, x + du, y + dv) in last and t - last[(b, x + du, y + dv)] <= dt
                 for du in (-1, 0, 1) for dv in (-1, 0, 1))
        keep.append(ok)
        last[(b, x, y)] = t
    return keep


def random_stream(gen, n, B, H, W, span_us, hot_px=()):
    """Random events in a small frame (dense enough for support) plus hot pixels that fire often; packed by
    element, time order within each."""
    rows = []
    for k in range(B):
        t = torch.sort(torch.randint(0, span_us, (n,), generator=gen)).values
        x = torch.randint(0, W, (n,), generator=gen)
        y = torch.randint(0, H, (n,), generator=gen)
        for i in range(n):
            if hot_px and i % 3 == 0:
                x[i], y[i] = hot_px[i % len(hot_px)]
        rows += [(k, int(x[i]), int(y[i]), int(t[i])) for i in range(n)]
    return rows


def as_tensors(rows):
    b, x, y, t = (torch.tensor([r[i] for r in rows], dtype=torch.int64) for i in range(4))
    return x.to(torch.int16), y.to(torch.int16), t, b


@pytest.mark.parametrize("B", [1, 3])
def test_matches_oracle_in_any_windows(B):
    gen = torch.Generator().manual_seed(B)
    H, W = 9, 11
    rows = random_stream(gen, 900, B, H, W, 60_000, hot_px=((2, 3), (8, 1)))
    params = dict(dt=800, period=10_000, ratio=4.0, min_count=5)
    want = oracle(rows, H, W, **params)
    assert 0.1 < sum(want) / len(want) < 0.9  # the test data exercises both outcomes
    x, y, t, b = as_tensors(rows)
    for cuts in ([len(rows)], [1, 50, 400, len(rows)], list(range(37, len(rows), 37)) + [len(rows)]):
        f = BackgroundActivityFilter(H, W, dt_us=800, hot_period_us=10_000, hot_ratio=4.0, hot_min_rate_hz=500,
                                     batch_size=B)
        assert f.hot_min_count == 5
        got, i0 = [], 0
        for i1 in cuts:
            got += f(x[i0:i1], y[i0:i1], t[i0:i1], b[i0:i1] if B > 1 else None).tolist()
            i0 = i1
        assert got == want
    assert bool(f.hot[0, 3, 2]) and bool(f.hot[0, 1, 8])  # the pixels that fire a third of all events


def test_hot_pixel_masked_and_noise_dropped_edge_kept():
    H, W = 40, 40
    f = BackgroundActivityFilter(H, W, dt_us=2000, hot_period_us=100_000)
    gen = torch.Generator().manual_seed(0)
    xs, ys, ts, kind = [], [], [], []
    for ms in range(400):  # a vertical edge sweeping right at 100 px/s, a hot pixel at 1 kHz, sparse noise
        t = ms * 1000
        col = (ms // 10) % W
        for r in range(5, 35):
            xs.append(col), ys.append(r), ts.append(t + r), kind.append("edge")
        xs.append(30), ys.append(2), ts.append(t + 500), kind.append("hot")
        if ms % 4 == 0:
            xs.append(int(torch.randint(0, W, (1,), generator=gen))), ys.append(int(torch.randint(0, H, (1,),
                                                                                               generator=gen)))
            ts.append(t + 700), kind.append("noise")
    keep = f(torch.tensor(xs), torch.tensor(ys), torch.tensor(ts))
    k = lambda name, since=0: torch.tensor([a == name and ts[i] >= since for i, a in enumerate(kind)])
    assert keep[k("edge")].float().mean() > 0.95
    assert keep[k("noise")].float().mean() < 0.1
    assert not keep[k("hot", since=100_000)].any()  # masked from the first check on
    assert bool(f.hot[0, 2, 30]) and int(f.hot.sum()) == 1


def test_reset_one_element_and_errors():
    f = BackgroundActivityFilter(4, 4, dt_us=100, batch_size=2)
    x, y, t, b = torch.tensor([0, 1, 0, 1]), torch.tensor([0, 0, 0, 0]), torch.tensor([0, 10, 0, 10]), \
        torch.tensor([0, 0, 1, 1])
    assert f(x, y, t, b).tolist() == [False, True, False, True]
    f.reset(torch.tensor([1]))
    assert f(torch.tensor([0, 0]), torch.tensor([1, 1]), torch.tensor([20, 20]), torch.tensor([0, 1])).tolist() \
        == [True, False]
    with pytest.raises(ValueError, match="x must lie"):
        f(torch.tensor([4]), torch.tensor([0]), torch.tensor([30]))
    assert int(f.last_us[0].max()) == 20  # nothing written by the failed call
    with pytest.raises(ValueError, match="positive"):
        denoise_update_(f.last_us, f.count, f.hot, f.period_end, x, y, t, b, dt_us=0)
