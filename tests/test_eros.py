"""EROS against a sequential per-event oracle (plain Python loops, float64)."""

import math

import numpy as np
import pytest
import scipy.ndimage
import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.stages.eros import (EROS, canvas_observation, eros_update, eros_update_, observation,
                                     recent_observation)
from torchevtrack.stages.template import to_canvas
from torchevtrack.stages.flow import NEVER


def eros_oracle(surface, xs, ys, bs, k, d):
    """The textbook definition: per event, multiply the clipped k x k window by lam, then set 1."""
    s = surface.astype(np.float64).copy()
    B, H, W = s.shape
    r = k // 2
    lam = d ** (1.0 / k)
    for x, y, b in zip(xs, ys, bs):
        for yy in range(max(y - r, 0), min(y + r, H - 1) + 1):
            for xx in range(max(x - r, 0), min(x + r, W - 1) + 1):
                s[b, yy, xx] *= lam
        s[b, y, x] = 1.0
    return s


def random_stream(rng, n, B, H, W, hot=0.0):
    x = rng.integers(0, W, n)
    y = rng.integers(0, H, n)
    if hot:  # force repeated pixels and border pixels
        m = rng.random(n) < hot
        x[m] = rng.choice([0, 1, W - 1, W // 2], m.sum())
        y[m] = rng.choice([0, H - 1, H // 2], m.sum())
    b = rng.integers(0, B, n)
    return x, y, b


@pytest.mark.parametrize("k,d", [(7, 0.3), (3, 0.5), (9, 0.75), (1, 0.4)])
@pytest.mark.parametrize("B", [1, 3])
def test_matches_sequential_oracle(k, d, B):
    rng = np.random.default_rng(k * 10 + B)
    H, W = 13, 17
    s0 = rng.random((B, H, W)).astype(np.float32)
    ref = s0.astype(np.float64)
    s = torch.from_numpy(s0)
    for n in (1, 40, 300, 0, 700):  # several packets, the state carries over
        x, y, b = random_stream(rng, n, B, H, W, hot=0.3)
        ref = eros_oracle(ref, x, y, b, k, d)
        s = eros_update(s, torch.from_numpy(x).short(), torch.from_numpy(y).short(),
                        torch.from_numpy(b), k, d)
        np.testing.assert_allclose(s.numpy(), ref, atol=1e-6, rtol=0)
    assert s.dtype == torch.float32 and s.shape == (B, H, W)


@pytest.mark.parametrize("k", [7, 3])
def test_sparse_write_path_small_packets_on_larger_sensor(k):
    # Few events on a larger sensor: the touched pixels are rewritten sparsely instead of a dense box.
    rng = np.random.default_rng(k)
    B, H, W = 2, 40, 64
    s0 = rng.random((B, H, W)).astype(np.float32)
    ref, s = s0.astype(np.float64), torch.from_numpy(s0)
    for n in (1, 3, 8, 20, 2):
        x, y, b = random_stream(rng, n, B, H, W, hot=0.3)
        ref = eros_oracle(ref, x, y, b, k, 0.3)
        s = eros_update(s, torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(b), k, 0.3)
        np.testing.assert_allclose(s.numpy(), ref, atol=1e-6, rtol=0)


def test_module_state_b_none_and_packet_split():
    rng = np.random.default_rng(1)
    H, W = 10, 12
    x, y, _ = random_stream(rng, 500, 1, H, W, hot=0.2)
    ref = eros_oracle(np.zeros((1, H, W)), x, y, np.zeros_like(x), 7, 0.3)
    m = EROS(H, W, kernel_size=7, decay=0.3)
    tx, ty = torch.from_numpy(x), torch.from_numpy(y)
    for i in range(0, 500, 37):  # split into uneven packets: the state must carry over
        out = m(tx[i:i + 37], ty[i:i + 37])
    assert out is m.surface
    np.testing.assert_allclose(m.surface.numpy(), ref, atol=1e-6, rtol=0)
    assert abs(m.lam - 0.3 ** (1 / 7)) < 1e-12
    m.reset()
    assert float(m.surface.abs().sum()) == 0.0


def test_functional_does_not_modify_input_and_inplace_does():
    s = torch.full((1, 5, 5), 0.5)
    x, y = torch.tensor([2]), torch.tensor([2])
    out = eros_update(s, x, y, None, 3, 0.5)
    assert float(s[0, 2, 2]) == 0.5 and float(out[0, 2, 2]) == 1.0
    assert float(out[0, 0, 0]) == 0.5 and abs(float(out[0, 1, 1]) - 0.5 * 0.5 ** (1 / 3)) < 1e-7
    eros_update_(s, x, y, None, 3, 0.5)
    assert torch.equal(s, out)


def test_interleaved_batches_are_independent():
    rng = np.random.default_rng(5)
    H, W, B = 9, 11, 2
    x, y, b = random_stream(rng, 400, B, H, W, hot=0.2)
    s = eros_update(torch.zeros(B, H, W), torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(b), 5, 0.4)
    for bb in range(B):
        m = b == bb
        ref = eros_oracle(np.zeros((1, H, W)), x[m], y[m], np.zeros(m.sum(), int), 5, 0.4)
        np.testing.assert_allclose(s[bb].numpy(), ref[0], atol=1e-6, rtol=0)


def test_observation_is_3x3_median():
    rng = np.random.default_rng(2)
    s = torch.from_numpy(rng.random((2, 8, 9)).astype(np.float32))
    ref = np.stack([scipy.ndimage.median_filter(s[i].numpy(), size=3, mode="mirror")  # = torch "reflect"
                    for i in range(2)])
    np.testing.assert_allclose(observation(s).numpy(), ref, atol=1e-7)


def test_bad_inputs():
    with pytest.raises(ValueError, match="kernel_size"):
        EROS(10, 10, kernel_size=4)
    with pytest.raises(ValueError, match="kernel_size"):
        EROS(10, 10, kernel_size=0)
    with pytest.raises(ValueError, match="decay"):
        EROS(10, 10, decay=1.0)
    m = EROS(10, 10, batch_size=2)
    with pytest.raises(ValueError, match="x must lie"):
        m(torch.tensor([10]), torch.tensor([0]))
    with pytest.raises(ValueError, match="b must lie"):
        m(torch.tensor([1]), torch.tensor([0]), torch.tensor([2]))
    with pytest.raises(TypeError, match="integer"):
        m(torch.tensor([1.0]), torch.tensor([0]))
    with pytest.raises(ValueError, match="shape"):
        m(torch.tensor([1, 2]), torch.tensor([0]))
    with pytest.raises(ValueError, match="contiguous"):
        eros_update_(torch.zeros(1, 6, 5).transpose(1, 2), torch.tensor([1]), torch.tensor([1]), None)


def _recent_reference(surface, last_us, origin, size, t_now, max_age_us, recency_us):
    """recent_observation by its definition: weigh each window's pixels by event age, then observation()."""
    h, w = size
    crops = []
    for i, (u0, v0) in enumerate(origin.tolist()):
        crop = surface[i, v0:v0 + h, u0:u0 + w]
        age = t_now[i] - last_us[i, :, v0:v0 + h, u0:u0 + w].amax(0)
        if max_age_us > 0:
            crop = crop * (age < max_age_us)
        tau = float(recency_us[i]) if isinstance(recency_us, torch.Tensor) else recency_us
        if tau > 0:
            crop = crop * torch.exp(-age.clamp_min(0).float() / tau)
        crops.append(crop)
    return observation(torch.stack(crops))


@pytest.mark.parametrize("size", [(37, 52), (1, 9), (8, 1)])
@pytest.mark.parametrize("max_age_us, recency_us", [(0, 0.0), (3000, 0.0), (0, 800.0), (3000, 800.0),
                                                    (3000, torch.tensor([800.0, 2500.0])),  # one per element
                                                    (0, torch.tensor([1200.0, 0.0]))])
@pytest.mark.parametrize("channels", [2, 1])  # the flow's SAE (a strided view), the EROS side's time surface
def test_recent_observation_matches_its_definition(size, max_age_us, recency_us, channels):
    gen = torch.Generator().manual_seed(21)
    B, H, W = 2, 60, 80
    surface = torch.rand(B, H, W, generator=gen) * (torch.rand(B, H, W, generator=gen) > 0.5)
    padded = torch.full((B, channels, H + 4, W + 4), NEVER, dtype=torch.int64)
    last = padded[:, :, 2:-2, 2:-2] if channels == 2 else padded[:, :, 2:-2, 2:-2].contiguous()
    # one channel: more pixels fired, and recently enough, that the median of the small windows keeps some
    fired = torch.rand(B, channels, H, W, generator=gen) > (0.3 if channels == 2 else 0.05)
    first = 0 if channels == 2 else 7500
    last.copy_(torch.where(fired, torch.randint(first, 10000, (B, channels, H, W), generator=gen), NEVER))
    origin = torch.tensor([[3, 5], [W - size[1], H - size[0]]])
    t_now = torch.tensor([10000, 9000])
    out = recent_observation(surface, last, origin, size, t_now, max_age_us, recency_us)
    ref = _recent_reference(surface, last, origin, size, t_now, max_age_us, recency_us)
    assert out.shape == (B, *size) and (ref > 0).any()
    assert torch.allclose(out, ref, rtol=1e-6, atol=1e-7)  # exp may round differently in the last bit
    with pytest.raises(ValueError, match="inside"):
        recent_observation(surface, last, origin + 1, size, t_now)
    with pytest.raises(ValueError, match="time surface"):
        recent_observation(surface, last.float(), origin, size, t_now)


@pytest.mark.parametrize("max_age_us, recency_us", [(0, 0.0), (3000, 800.0),
                                                    (3000, torch.tensor([2500.0, 800.0, 0.0]))])
@pytest.mark.parametrize("channels", [2, 1])
def test_canvas_observation_is_the_recent_observation_of_the_tap_window_in_the_canvas(max_age_us, recency_us,
                                                                                      channels):
    gen = torch.Generator().manual_seed(5)
    B, H, W, N = 3, 60, 80, 24
    surface = torch.rand(B, H, W, generator=gen) * (torch.rand(B, H, W, generator=gen) > 0.4)
    last = torch.where(torch.rand(B, channels, H, W, generator=gen) > 0.3,
                       torch.randint(0, 10000, (B, channels, H, W), generator=gen), NEVER)
    t_now = torch.tensor([10000, 9000, 9500])
    # inside the frame at 2.3 frame px per canvas px (the taps skip rows and columns, whose medians the kernel
    # leaves out); over the top-left corner; wholly outside the frame
    box = torch.tensor([[40.3, 31.2, 56.0], [3.0, 4.5, 30.0], [-50.0, 20.0, 20.0]], dtype=torch.float64)
    out = canvas_observation(surface, last, box, N, t_now, max_age_us, recency_us)
    assert out.shape == (B, N, N) and out.dtype == torch.float32
    assert (out[2] == 0).all() and (out[0] > 0).any()
    for i, (cu, cv, side) in enumerate(box[:2].tolist()):  # the oracle: the window under the taps, then to_canvas
        s = side / N
        u0, v0 = max(math.floor(cu + (0.5 - N / 2) * s), 0), max(math.floor(cv + (0.5 - N / 2) * s), 0)
        u1, v1 = min(math.floor(cu + (N / 2 - 0.5) * s) + 2, W), min(math.floor(cv + (N / 2 - 0.5) * s) + 2, H)
        origin = torch.tensor([[u0, v0]])
        win = _recent_reference(surface[i:i + 1], last[i:i + 1], origin, (v1 - v0, u1 - u0), t_now[i:i + 1],
                                max_age_us, recency_us[i:i + 1] if isinstance(recency_us, torch.Tensor) else recency_us)
        ref = to_canvas(win, box[i:i + 1].float(), N, origin)
        assert torch.allclose(out[i:i + 1], ref, atol=2e-6), (out[i:i + 1] - ref).abs().max()
    with pytest.raises(ValueError, match="box"):
        canvas_observation(surface, last, box[:2], N, t_now)


def test_rows_update_only_their_elements():
    """forward(x, y, b, rows=) applies a share's events (b counted from its start) to those rows only."""
    gen = torch.Generator().manual_seed(8)
    x, y, b = torch.randint(0, 12, (200,), generator=gen), torch.randint(0, 10, (200,), generator=gen), \
        torch.randint(0, 3, (200,), generator=gen)
    whole, part = EROS(10, 12, batch_size=3), EROS(10, 12, batch_size=3)
    whole(x, y, b)
    mine = b >= 1
    out = part(x[mine], y[mine], b[mine] - 1, rows=slice(1, 3))
    assert out.shape == (2, 10, 12) and torch.equal(part.surface[1:], whole.surface[1:])
    assert (part.surface[0] == 0).all()


def test_time_surface_is_the_newest_event_per_pixel():
    """TimeSurface against a loop over the events: the newest time of each pixel, any polarity, per element."""
    from torchevtrack.stages.eros import TimeSurface

    gen = torch.Generator().manual_seed(4)
    H, W, B, n = 7, 9, 3, 400
    x, y = torch.randint(0, W, (n,), generator=gen), torch.randint(0, H, (n,), generator=gen)
    b = torch.randint(0, B, (n,), generator=gen)
    t = torch.randint(0, 10_000, (n,), generator=gen)  # not sorted: the newest is the largest, in any order
    ts = TimeSurface(H, W, batch_size=B)
    out = ts(x, y, t, b)
    want = [[[NEVER] * W for _ in range(H)] for _ in range(B)]
    for xi, yi, ti, bi in zip(x.tolist(), y.tolist(), t.tolist(), b.tolist()):
        want[bi][yi][xi] = max(want[bi][yi][xi], ti)
    assert out is ts.last_us and out.tolist() == want
    ts(x[:5], y[:5], t[:5] + 20_000, rows=slice(2, 3))  # element 2 alone, b counted from the first row
    for xi, yi, ti in zip(x[:5].tolist(), y[:5].tolist(), t[:5].tolist()):
        want[2][yi][xi] = max(want[2][yi][xi], ti + 20_000)
    assert ts.last_us.tolist() == want
    ts.reset(torch.tensor([False, True, False]))
    want[1] = [[NEVER] * W for _ in range(H)]
    assert ts.last_us.tolist() == want
    with pytest.raises(ValueError, match="y must lie"):
        ts(x, y + H, t, b)
    with pytest.raises(TypeError, match="int64"):
        ts(x, y, t.int(), b)
    assert ts.last_us.tolist() == want  # nothing written
    ts.reset()
    assert bool((ts.last_us == NEVER).all())


def _follow_reference(flow, valid, px, min_us, max_us):
    """The window a speed asks for, element by element: px over the upper quartile of the valid vectors' speeds,
    clamped; None with fewer than three vectors."""
    out = []
    for f, v in zip(flow.tolist(), valid.tolist()):
        speeds = [math.hypot(*fg) for fg, ok in zip(f, v) if ok]
        out.append(None if len(speeds) < 3 else min(max(px / max(float(np.percentile(speeds, 75)), 1e-6) * 1e6, min_us),
                                                    max_us))
    return out


def test_recency_follows_the_flow_speed_on_its_grid():
    """Recency against the per-element reference over a run of random flow fields: each call moves an element with
    three or more valid vectors to the 250 us multiple nearest its window, the others keep theirs; reset restores
    the start; fixed windows never move."""
    from torchevtrack.stages.eros import Recency, follow_speed

    gen = torch.Generator().manual_seed(8)
    B, G, px = 4, 12, 2.5
    rec = Recency(B, 2500.0, px=px, min_us=1250, max_us=10000)
    fixed = Recency(B, 2500.0)
    want = [2500.0] * B
    assert rec.window_us.tolist() == want and len(rec.windows_us) == 36
    for _ in range(20):
        flow = torch.randn(B, G, 2, generator=gen) * torch.rand(B, 1, 1, generator=gen) * 3000
        valid = torch.rand(B, G, generator=gen) < torch.rand(B, 1, generator=gen)
        valid[0, :2], valid[0, 2:] = True, False  # two vectors: not enough
        ref = _follow_reference(flow, valid, px, 1250.0, 10000.0)
        got = follow_speed(flow, valid, px, 1250.0, 10000.0)
        for k, r in enumerate(ref):
            if r is not None:
                want[k] = 250.0 * round(r / 250.0)
            assert (r is None and math.isnan(got[k])) or got[k] == want[k]
        assert rec(flow, valid).tolist() == want
        assert fixed(flow, valid).tolist() == [2500.0] * B
    assert want[0] == 2500.0 and len(set(want)) > 1
    rec.reset(torch.tensor([1, 3]))
    assert rec.window_us.tolist() == [want[0], 2500.0, want[2], 2500.0]
    rec.reset()
    assert rec.window_us.tolist() == [2500.0] * B
    with pytest.raises(ValueError, match="flow"):
        rec(torch.zeros(B, G), valid)
    with pytest.raises(ValueError, match="multiples of 250"):
        Recency(1, 2600.0, px=2.5)
    with pytest.raises(ValueError, match="min_us <= recency_us"):
        Recency(1, 500.0, px=2.5)
    with pytest.raises(ValueError, match="eros.recency"):
        TrackerConfig().replace(eros={"recency_px": 2.5, "recency_max_us": 2000.0})
    # no weighting (the paper's observation) with the default px: nothing to follow, the window stays 0
    paper = Recency.from_config(TrackerConfig().replace(eros={"recency_us": 0.0}).eros, batch_size=2)
    assert TrackerConfig().eros.recency_px > 0 and paper.windows_us == (0.0,) and paper.px == 0
    assert paper(flow[:2], valid[:2]).tolist() == [0.0, 0.0]
