"""Per-update cost of config changes: two trackers, the defaults and the changed config, updated window by window.

This machine's speed drifts by 25 % and more within minutes, so paired ``bench`` runs resolve a cost of a few per
cent poorly. Here both trackers run in one process on the same windows of one sequence, alternating update by
update (which one goes first alternates too), without the pipeline thread (the measured cost is the update's own).
Each round restarts both at the first true pose; the first round warms up and the first ``--skip`` updates of each
round are left out. Printed: the mean and median milliseconds per update of each, their ratios (changed / defaults)
and the changed tracker's stage times that the defaults have not (e.g. ``loss``, ``recover``).

    .venv/bin/python tools/option_cost.py data/bench/potted_fast --set loss.enabled=true --set recover.enabled=true

Run from the repository, with the project's virtual environment.
"""

from __future__ import annotations

import argparse
import collections
import statistics
import time

import numpy as np
import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", help="sequence directory")
    ap.add_argument("--set", action="append", required=True, metavar="KEY=VALUE", help="the change (repeatable)")
    ap.add_argument("--updates", type=int, default=250, help="updates per round (default 250)")
    ap.add_argument("--rounds", type=int, default=3, help="measured rounds after the warm-up (default 3)")
    ap.add_argument("--skip", type=int, default=10, help="updates left out at the start of each round (default 10)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    seq = Sequence.load(args.seq)
    configs = {"defaults": TrackerConfig(), "changed": TrackerConfig().override(args.set)}
    trackers = {k: EventPoseTracker(seq.camera, seq.mesh, c, pipeline=False) for k, c in configs.items()}
    ev, period = seq.events, trackers["defaults"].period_us
    t = ev.t.numpy()
    t0 = int(seq.gt_t_us[0])
    windows = []
    for k in range(args.updates):
        i0, i1 = np.searchsorted(t, [t0 + k * period, t0 + (k + 1) * period])
        windows.append((ev.x[i0:i1], ev.y[i0:i1], ev.t[i0:i1], ev.p[i0:i1], t0 + (k + 1) * period))
    ms = {k: [] for k in trackers}
    stages = {k: collections.Counter() for k in trackers}
    for r in range(args.rounds + 1):
        for tracker in trackers.values():
            tracker.reset(seq.gt_poses[0].double())
        for j, (x, y, tt, p, end) in enumerate(windows):
            for k in (("defaults", "changed") if j % 2 else ("changed", "defaults")):
                start = time.perf_counter()
                trackers[k](x, y, tt, p, t_us=end)
                if r > 0 and j >= args.skip:
                    ms[k].append((time.perf_counter() - start) * 1e3)
                    stages[k].update(trackers[k].stage_ms)
    n = len(ms["defaults"])
    mean = {k: statistics.fmean(v) for k, v in ms.items()}
    for k in trackers:
        print(f"{k:9s} {mean[k]:.3f} ms per update (median {statistics.median(ms[k]):.3f}), {n} updates")
    extra = {s: v / n for s, v in stages["changed"].items() if s not in stages["defaults"]}
    med = {k: statistics.median(v) for k, v in ms.items()}
    print(f"ratio changed / defaults: means {mean['changed'] / mean['defaults']:.3f}, medians "
          f"{med['changed'] / med['defaults']:.3f}; the change's own stages (ms per update): "
          + (", ".join(f"{s} {v:.3f}" for s, v in extra.items()) or "none"))
    for tracker in trackers.values():
        tracker.close()


if __name__ == "__main__":
    main()
