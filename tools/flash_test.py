"""What does a 2 ms flash (every pixel firing) do to the tracker, with and without the burst guard?

Loads a sequence directory, optionally injects a flash of ``--flash-events`` events (every pixel fires about the
same number of times, at uniform random times in ``[t_flash, t_flash + 2 ms)``, random polarity), and tracks the
first ``--duration`` seconds update by update (``forward`` per window, so each update's time is its own). Mode
``flash`` turns the tracker's burst guard off (``burst.enabled: false``); ``guard`` and ``none`` run the default
config, whose guard drops a burst window's events before any stage. Prints the longest update, the flash windows' update times, the peak RSS
growth during tracking, and the errors 0.2 s after the flash. Run each mode in its own process (peak RSS).

    python tools/flash_test.py SEQDIR --mode none|flash|guard [--duration 1.0] [--flash-at 0.5]
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.metrics import per_pose_errors
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker


def inject_flash(ev, width: int, height: int, t_us: int, n: int, seed: int = 0):
    """The stream's events with a 2 ms flash of about ``n`` events merged in (time order)."""
    gen = torch.Generator().manual_seed(seed)
    k = max(1, round(n / (width * height)))
    yy, xx = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    x = xx.reshape(-1).repeat(k).to(ev.x.dtype)
    y = yy.reshape(-1).repeat(k).to(ev.y.dtype)
    t = t_us + torch.randint(0, 2000, (x.numel(),), generator=gen)
    p = torch.randint(0, 2, (x.numel(),), generator=gen).to(ev.p.dtype)
    tt = torch.cat((ev.t, t))
    order = torch.argsort(tt, stable=True)
    return torch.cat((ev.x, x))[order], torch.cat((ev.y, y))[order], tt[order], torch.cat((ev.p, p))[order], x.numel()


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir")
    ap.add_argument("--mode", choices=("none", "flash", "guard"), required=True)
    ap.add_argument("--duration", type=float, default=1.0)
    ap.add_argument("--flash-at", type=float, default=0.5, help="seconds after the first pose (+1 ms: two windows)")
    ap.add_argument("--flash-events", type=int, default=2_000_000)
    args = ap.parse_args()
    torch.set_num_threads(1)

    seq = Sequence.load(args.seqdir)
    cam, ev = seq.camera, seq.events
    t0 = int(seq.gt_t_us[0])
    t_flash = t0 + round(args.flash_at * 1e6) + 1000
    if args.mode == "none":
        x, y, t, p, n_flash = ev.x, ev.y, ev.t, ev.p, 0
    else:
        x, y, t, p, n_flash = inject_flash(ev, cam.width, cam.height, t_flash, args.flash_events)
    cfg = TrackerConfig().replace(burst={"enabled": args.mode != "flash"})
    tracker = EventPoseTracker(cam, seq.mesh, cfg)
    period = tracker.period_us
    n = round(args.duration * 1e6) // period
    bounds = torch.searchsorted(t, t0 + torch.arange(n + 1) * period)
    tracker.reset(seq.gt_poses[0])
    base = rss_mb()
    times, poses, ms, dropped = [], [], [], 0
    for i in range(n):
        a, b = int(bounds[i]), int(bounds[i + 1])
        start = time.perf_counter()
        pose = tracker(x[a:b], y[a:b], t[a:b], p[a:b], t_us=t0 + (i + 1) * period)
        if tracker.quality.burst is not None and bool(tracker.quality.burst[0]):
            dropped += b - a
        ms.append((time.perf_counter() - start) * 1e3)
        times.append(t0 + (i + 1) * period)
        poses.append(pose[0])
    tracker.close()
    peak = rss_mb()
    e = per_pose_errors(torch.tensor(times), torch.stack(poses), seq.gt_t_us, seq.gt_poses)
    k = int(torch.searchsorted(e["t_us"], torch.tensor(t_flash + 200_000)))
    after = slice(k, None)
    i_f = (t_flash - t0) // period
    print(f"{args.seqdir} mode={args.mode} flash_events={n_flash} dropped={dropped}")
    flash_ms = [round(v, 1) for v in ms[i_f:i_f + 3]]
    print(f"update ms (the first, compiling, left out): max {max(ms[1:]):.1f}, flash windows {flash_ms}, "
          f"p99 {sorted(ms[1:])[int(0.99 * (len(ms) - 1))]:.2f}; peak RSS growth while tracking {peak - base:.0f} MB "
          f"(peak {peak:.0f} MB)")
    te, re = e["te"], e["re"]
    print(f"error at flash + 0.2 s: {float(te[k]) * 100:.2f} cm / {math.degrees(float(re[k])):.2f} deg; "
          f"RMSE from then on {float(te[after].square().mean().sqrt()) * 100:.2f} cm / "
          f"{math.degrees(float(re[after].square().mean().sqrt())):.2f} deg; "
          f"whole run {float(te.square().mean().sqrt()) * 100:.2f} cm / "
          f"{math.degrees(float(re.square().mean().sqrt())):.2f} deg")


if __name__ == "__main__":
    main()
