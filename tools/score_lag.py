"""How far does the template score's maximum lie from the true pose? The correction's lag, per axis.

Feeds a sequence's events to the tracker (whose EROS and time surface do not depend on its poses) and
every ``--every`` updates renders the object at the ground-truth pose, fits the correction's quadratic
score model to the current observation there and finds, per axis alone, the best of the steps
``-k .. k`` (``--range``; 1 px / 0.5 deg hypothesis steps). With an observation that showed the object
where it is now, the best step would be 0 on every axis; EROS keeps ~30 ms of edges, so on a moving
object the maximum lags behind. Prints the best steps per sample, then their mean and mean magnitude per
axis (tx ty tz rx ry rz). Compare observations with ``--recency-us`` (``eros.recency_us``).

    .venv/bin/python tools/score_lag.py data/bench/cracker_regular --duration 2 --recency-us 2500
"""

from __future__ import annotations

import argparse

import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.stages.template import AXES, hypothesis_steps
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir")
    ap.add_argument("--duration", type=float, default=2.0, help="seconds from the first pose")
    ap.add_argument("--recency-us", type=float, default=None, help="eros.recency_us (default: the config's)")
    ap.add_argument("--every", type=int, default=25, help="updates between samples")
    ap.add_argument("--range", type=int, default=4, help="largest step tried per axis")
    ap.add_argument("--config", help="tracker config YAML (default: the defaults)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    seq = Sequence.load(args.seqdir)
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    if args.recency_us is not None:
        cfg = cfg.replace(eros={"recency_us": args.recency_us})
    tracker = EventPoseTracker(seq.camera, seq.mesh, cfg)
    gt_t, gt = seq.gt_t_us, seq.gt_poses
    t0, period = int(gt_t[0]), tracker.period_us
    tracker.reset(gt[0])
    n = round(args.duration * 1e6) // period
    bounds = torch.searchsorted(seq.events.t, t0 + torch.arange(n + 1) * period)
    k = torch.arange(-args.range, args.range + 1, dtype=torch.float64)
    best = []
    for i in range(n):
        w = seq.events[int(bounds[i]):int(bounds[i + 1])]
        tracker(w.x.long(), w.y.long(), w.t, w.p.long())
        if (i + 1) % args.every:
            continue
        j = int(torch.searchsorted(gt_t, t0 + (i + 1) * period).clamp(max=len(gt_t) - 1))
        pose = gt[j:j + 1]
        render, origin = tracker._render(pose, shaded=True)
        model = tracker.corrector.template_model(pose.float(), render.depth, render.gray, origin)
        quad = model.fit(tracker._observation(origin, render.depth.shape[-2:], tracker.t_last), origin)
        unit = hypothesis_steps(pose, seq.camera, model.gain)[0, 1::2]  # (6, 6): one + step per axis
        row = [int(k[quad.at_steps((k[:, None] * unit[a])[None])[0].argmax()]) for a in range(6)]
        best.append(row)
        print(f"t = {(i + 1) * period / 1e6:5.2f} s  best step {row}")
    tracker.close()
    b = torch.tensor(best, dtype=torch.float64)
    print("axis        " + " ".join(f"{a:>6s}" for a in AXES))
    print("mean        " + " ".join(f"{v:6.2f}" for v in b.mean(0).tolist()))
    print("mean |step| " + " ".join(f"{v:6.2f}" for v in b.abs().mean(0).tolist()))


if __name__ == "__main__":
    main()
