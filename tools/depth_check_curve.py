"""The depth check's operating curve from a benchmark's saved runs: failures flagged in time against false alarms,
for other rivals, check periods and margins than the defaults, without tracking again.

The check (:class:`torchevtrack.recover.Recoverer`, ``recover.check_us``, ``recover.check_margin_px``) flags an
element whose pose costs more than a depth rival by the margin (:meth:`Relocaliser.rivals`). The flags change no
pose, so a benchmark's saved first-draw poses (``OUT/poses/no_ukf/S.txt``) are what the tracker would have checked
with any setting. Every ``--grid`` ms of each sequence this tool costs the saved pose against every ``--depths``
rival (wholly in view only, as the check), on the newest-event surface of the sequence's raw events (the tracker's
own surface also skips burst windows), then replays the flag for each subset of rivals, period and margin:

* within 50 ms: failed runs (the benchmark's failure rule, ``results.json``) whose flag was up at some instant of
  the 50 ms from the failure run's start (raised by a check before it and not cleared, or raised within);
* flagged: failed runs flagged at any instant from the failure run's start;
* false alarms / min: flag episodes that closed before the failure run began (all, in a run that never failed),
  per minute tracked up to the failure (or the end).

The check alone is replayed: the loss detector's own declarations (which ``tracker.lost`` adds) are not.

    .venv/bin/python tools/depth_check_curve.py dev_out data/wide_dev fresh_out data/wide_fresh \\
        --subsets 0.8,1.25 0.9,1.1 0.8,0.9,1.1,1.25 --periods 20,50 --margins 0.25,0.5,1

Run from the repository, with the project's virtual environment.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchevtrack.config import TrackerConfig
from torchevtrack.io.poses import read_tum
from torchevtrack.recover import wholly_in_view
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker

WITHIN_US = 50_000


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


def check_costs(out: Path, data: Path, method: str, depths: tuple[float, ...], grid_us: int) -> dict:
    """Per sequence of the benchmark ``out``: ``t0``, ``fail`` (us or None) and ``rows`` ``[t, own, rivals...]`` every
    ``grid_us`` (NaN costs where the pose is not wholly in view)."""
    results = json.loads((out / "results.json").read_text())
    cfg = TrackerConfig().replace(loss={"enabled": True}, recover={"enabled": True})
    runs = {}
    for name, x in tqdm(sorted(results["results"][method].items()), desc="sequences", unit="seq"):
        seq = Sequence.load(data / name)
        t, poses = read_tum(out / x["pose_file"])
        tracker = EventPoseTracker(seq.camera, str(data / name / "mesh.ply"), cfg)
        reloc = tracker.recover.relocalisers[0]
        ex, ey, et = (seq.events.x.numpy().astype(np.int64), seq.events.y.numpy().astype(np.int64),
                      seq.events.t.numpy())
        surface = np.full((seq.camera.height, seq.camera.width), -(2 ** 62), np.int64)
        t0, times, rows, j = results["sequences"][name]["t_start_us"], t.numpy(), [], 0
        for tau in range(t0 + grid_us, int(times[-1]) + 1, grid_us):
            k = int(np.searchsorted(et, tau, side="right"))
            surface[ey[j:k], ex[j:k]] = et[j:k]  # time-sorted: the newest event of a pixel is written last
            j = k
            i = int(np.searchsorted(times, tau))
            if i >= len(times) or times[i] != tau:
                continue
            pose = poses[i:i + 1]
            if wholly_in_view(pose, reloc):
                rows.append([tau] + reloc.rivals(pose, torch.from_numpy(surface.copy()), tau, depths).tolist())
            else:
                rows.append([tau] + [math.nan] * (1 + len(depths)))
        tracker.close()
        runs[name] = {"t0": t0, "fail": x["loss"]["first_failure_us"], "rows": rows}
    return runs


def replay(runs: dict, columns: list[int], period_us: int, margin_px: float) -> dict:
    """The flag of a check every ``period_us`` with the rivals in ``columns`` of the rows: the curve's counts."""
    within = flagged = failed = false = 0
    minutes = 0.0
    for x in runs.values():
        t0, fail, state, hist = x["t0"], x["fail"], False, []
        for row in x["rows"]:
            if (row[0] - t0) % period_us:
                continue
            if not math.isnan(row[1]):  # no check where the pose is not wholly in view: the flag stays
                state = min(row[c] for c in columns) < row[1] - margin_px
            hist.append((row[0], state))
        end = fail if fail is not None else (x["rows"][-1][0] if x["rows"] else t0)
        minutes += (end - t0) / 60e6
        last = False
        for tau, s in hist:
            if tau > end:
                break
            false += last and not s
            last = s
        if fail is None:
            false += last
            continue
        failed += 1
        before = [s for tau, s in hist if tau <= fail]
        up = bool(before and before[-1])
        within += up or any(s for tau, s in hist if fail < tau <= fail + WITHIN_US)
        flagged += up or any(s for tau, s in hist if tau > fail)
    return {"failed": failed, "within": within, "flagged": flagged,
            "false_per_min": false / minutes if minutes else 0.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", type=Path, nargs="+", metavar="OUT DATA",
                    help="a benchmark's output directory (results.json, poses/) and the directory of its sequences; "
                    "several pairs are pooled")
    ap.add_argument("--method", default="no_ukf", help="the method whose poses are checked (default no_ukf)")
    ap.add_argument("--depths", type=_floats, default=(0.8, 0.9, 1.1, 1.25),
                    help="rivals costed: depth factors along the line of sight (default 0.8,0.9,1.1,1.25)")
    ap.add_argument("--subsets", type=_floats, nargs="+", default=[(0.8, 1.25), (0.9, 1.1), (0.8, 0.9, 1.1, 1.25)],
                    help="subsets of --depths replayed (default: 0.8,1.25  0.9,1.1  all four)")
    ap.add_argument("--grid", type=int, default=10, help="ms between costed instants (default 10)")
    ap.add_argument("--periods", type=lambda s: [int(v) for v in s.split(",")], default=[20, 50],
                    help="check periods replayed, ms, multiples of --grid (default 20,50)")
    ap.add_argument("--margins", type=_floats, default=(0.25, 0.5, 1.0), help="margins replayed, px")
    ap.add_argument("--save", type=Path, help="also write the costs as JSON")
    args = ap.parse_args()
    torch.set_num_threads(1)
    for sub in args.subsets:
        if not set(sub) <= set(args.depths):
            ap.error(f"--subsets {','.join(map(str, sub))} is not within --depths {args.depths}")
    for p in args.periods:
        if p % args.grid:
            ap.error(f"--periods {p} ms is not a multiple of --grid {args.grid} ms")
    if len(args.pairs) % 2:
        ap.error("give each benchmark output directory with its data directory: OUT DATA [OUT DATA ...]")
    runs = {}
    for out, data in zip(args.pairs[::2], args.pairs[1::2]):
        runs.update({f"{out}/{name}": x
                     for name, x in check_costs(out, data, args.method, args.depths, args.grid * 1000).items()})
    if args.save:
        args.save.write_text(json.dumps(runs))
    print("| rivals | period (ms) | margin (px) | failed runs | flagged within 50 ms | flagged | false alarms / min |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for sub in args.subsets:
        columns = [2 + args.depths.index(f) for f in sub]
        for period in args.periods:
            for margin in args.margins:
                r = replay(runs, columns, period * 1000, margin)
                print(f"| {', '.join(f'x {f:g}' for f in sub)} | {period} | {margin:g} | {r['failed']} | {r['within']} "
                      f"| {r['flagged']} | {r['false_per_min']:.2f} |")


if __name__ == "__main__":
    main()
