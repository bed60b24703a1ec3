"""Throughput of stage 1 (EROS and its time surface) and stage 2 (SAE, triplet flow) on a 640x480 sensor.

Events: a bar rotating about the image centre (every pixel fires when the bar crosses it, radii
20..230 px) plus 10 % uniform noise, at a chosen event rate; processed in fixed-duration packets like
the tracker (2 ms = 500 Hz) and once as big packets of 100k events. Prints microseconds per packet
and events/s for each piece.

    .venv/bin/python tools/bench_eros_flow.py [--rates 0.5 1 2] [--window-us 2000] [--threads 2]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from torchevtrack.stages.eros import EROS, TimeSurface
from torchevtrack.stages.flow import TripletFlow, sae_update_

H, W = 480, 640


def rotating_bar_stream(rate_meps: float, duration_s: float, noise: float = 0.1, seed: int = 0):
    """Packed (x, y, t) int64 arrays of a rotating bar firing ``rate_meps`` million events/s on average."""
    yy, xx = np.mgrid[0:H, 0:W]
    rx, ry = xx - (W - 1) / 2, yy - (H - 1) / 2
    rho = np.hypot(rx, ry)
    m = (rho >= 20) & (rho <= 230)
    phi = np.mod(np.arctan2(ry, rx), math.pi)[m]
    px, py = xx[m], yy[m]
    omega = math.pi * rate_meps * 1e6 * (1 - noise) / m.sum()  # one half turn fires every pixel once
    half = math.pi / omega
    turns = math.ceil(duration_s / half)
    t = np.concatenate([np.round((phi + k * math.pi) / omega * 1e6) for k in range(turns)]).astype(np.int64)
    x, y = np.tile(px, turns), np.tile(py, turns)
    rng = np.random.default_rng(seed)
    n_noise = int(noise * len(t))
    x = np.concatenate([x, rng.integers(0, W, n_noise)])
    y = np.concatenate([y, rng.integers(0, H, n_noise)])
    t = np.concatenate([t, rng.integers(0, int(t.max()) + 1, n_noise)])
    o = np.argsort(t, kind="stable")
    x, y, t = x[o], y[o], t[o]
    k = t < duration_s * 1e6
    return torch.from_numpy(x[k]), torch.from_numpy(y[k]), torch.from_numpy(t[k])


def packets_by_time(t: torch.Tensor, window_us: int):
    edges = torch.arange(int(t[0]), int(t[-1]) + window_us, window_us)
    idx = torch.searchsorted(t, edges).tolist()
    return list(zip(idx[:-1], idx[1:]))


def packets_by_count(n: int, size: int):
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def bench(name, packets, fn, warmup=3):
    for a, b in packets[:warmup]:
        fn(a, b)
    t0 = time.perf_counter()
    for a, b in packets[warmup:]:
        fn(a, b)
    dt = time.perf_counter() - t0
    n = sum(b - a for a, b in packets[warmup:])
    k = len(packets) - warmup
    print(f"  {name:<26s} {dt / k * 1e6:9.0f} us/packet  {n / dt / 1e6:7.2f} M events/s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="M events/s")
    ap.add_argument("--window-us", type=int, default=2000)
    ap.add_argument("--duration", type=float, default=0.25, help="seconds of stream per rate")
    ap.add_argument("--big", type=int, default=100_000, help="events per big packet")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    print(f"{W}x{H}, torch {torch.__version__}, {a.threads} threads")
    runs = [(f"{r:g} Mev/s, {a.window_us} us packets", r, None) for r in a.rates]
    runs.append((f"{a.big} events per packet", max(a.rates), a.big))
    for title, rate, size in runs:
        x, y, t = rotating_bar_stream(rate, a.duration if size is None else max(a.duration, 4 * size / (rate * 1e6)))
        p = torch.ones_like(x, dtype=torch.int8)
        packets = packets_by_time(t, a.window_us) if size is None else packets_by_count(len(t), size)
        mean_n = np.mean([b - a_ for a_, b in packets])
        print(f"{title}: {len(packets)} packets, {mean_n:.0f} events each")
        eros = EROS(H, W, kernel_size=7, decay=0.3)
        bench("EROS", packets, lambda i, j: eros(x[i:j], y[i:j]))
        sae = torch.zeros(1, 1, H, W, dtype=torch.int64)
        bench("SAE", packets, lambda i, j: sae_update_(sae, x[i:j], y[i:j], t[i:j], None))
        flow = TripletFlow(H, W)
        bench("triplet flow (incl. SAE)", packets, lambda i, j: flow(x[i:j], y[i:j], t[i:j], p[i:j]))
        both = EROS(H, W)
        sae2 = torch.zeros(1, 1, H, W, dtype=torch.int64)
        bench("EROS + SAE", packets,
              lambda i, j: (both(x[i:j], y[i:j]), sae_update_(sae2, x[i:j], y[i:j], t[i:j], None)))
        stage1, times = EROS(H, W), TimeSurface(H, W)
        bench("EROS + time surface (stage 1)", packets,
              lambda i, j: (stage1(x[i:j], y[i:j]), times(x[i:j], y[i:j], t[i:j])))
        f = flow(x[packets[-1][0]:packets[-1][1]], y[packets[-1][0]:packets[-1][1]],
                 t[packets[-1][0]:packets[-1][1]], p[packets[-1][0]:packets[-1][1]])
        print(f"  last packet: {int(f.count.sum())} triplet samples, {int(f.valid.sum())} valid blocks")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
