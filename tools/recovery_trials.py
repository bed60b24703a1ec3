"""Issue 25's recovery targets, measured on the sequences of a benchmark directory.

Two kinds of trial, each judged against the ground truth at one instant (within ``--max-cm`` and ``--max-deg``;
the rotation about a hidden symmetry axis of an untextured symmetric object left out, as the benchmark does):

* ``start``: the tracker starts ``--offset-mm`` millimetres and ``--offset-deg`` degrees off the first true pose
  (random directions, :func:`~torchevtrack.geometry.perturb_pose`, ``--draws`` per sequence, seeds 0, 1, ...) and
  must be there ``--settle`` seconds later. One more element of the batch starts at the true pose: its error at
  that instant tells a start that missed the basin from one that reached it and shares the tracker's own error
  there (printed per sequence as ``from the truth``).
* ``blackout``: started at the true pose, the events of ``[--at, --at + --gap-ms)`` are removed while the object
  keeps moving, and the tracker must be there ``--settle`` seconds after the events return. A trial whose tracker
  was already off before the gap (at ``--at``) is reported but not counted; how far the object moved in the gap is
  printed, and the trials where it moved at most 10 cm (issue 25's 4-10 cm) are also counted apart. One more element
  of the batch tracks the same sequence without the gap (``without the gap``): a miss whose reference misses too is
  the tracker's own error at that instant, not a failed recovery.

* ``away``: on sequences made with ``synth --leave-view START,AWAY`` (the object slides out of the view and back,
  ``meta.json``'s ``leave_view``), started at the true pose, the tracker must be there ``--settle`` seconds after the
  object is fully back (``back_on_path_s``: ``START + AWAY + 2 SLIDE_S``). A trial already off when the object starts
  to leave is reported but not counted. There is no reference without the excursion.

Every trial also prints when its error first came within the bounds after the start (or after the gap), if it did
by the judged instant (``reached ... ms``): "reach within 0.2 s" read as a first arrival, where the judged instant
asks that it still be there. Each sequence's draws run as one batch; the loss detector runs (passively unless
``recover.enabled``) and each trial's count of updates flagged lost is printed. ``--set`` changes the tracker config
as ``track --set`` does, e.g. ``--set recover.enabled=true --set loss.enabled=true --set recover.start_search=true``.

    python tools/recovery_trials.py DIR --mode start [--draws 5] [--only A,B] [--set KEY=VALUE ...]
    python tools/recovery_trials.py DIR --mode blackout [--at 0.3] [--gap-ms 200] [--settle 0.1]
    python tools/recovery_trials.py DIR --mode away [--settle 0.2]
"""

from __future__ import annotations

import argparse
import math

import torch

from torchevtrack.benchmark import find_sequences
from torchevtrack.config import TrackerConfig
from torchevtrack.geometry import interpolate_poses, perturb_pose
from torchevtrack.mesh import hidden_symmetry_axis
from torchevtrack.metrics import per_pose_errors
from torchevtrack.synth.sequence import Sequence
from torchevtrack.synth.trajectory import back_on_path_s
from torchevtrack.tracker import EventPoseTracker


MAX_MOVED_CM = 10.0  # issue 25's blackouts: the object moves 4-10 cm in the gap; farther is reported apart


def errors(seq: Sequence, axis, t_us: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The evaluated times (us), translation (cm) and rotation (deg, about ``axis`` left out: the sequence's hidden
    symmetry axis or ``None``) errors of ``poses`` at ``t_us`` against the sequence's truth."""
    e = per_pose_errors(t_us, poses, seq.gt_t_us, seq.gt_poses,
                        symmetry_axis=None if axis is None else torch.as_tensor(axis))
    rot = e["re_sym"] if "re_sym" in e else e["re"]
    return e["t_us"], e["te"] * 100.0, torch.rad2deg(rot)


def error_at(seq: Sequence, axis, t_us: torch.Tensor, poses: torch.Tensor, t_query: int) -> tuple[float, float]:
    """The :func:`errors` (cm, deg) of the last pose at or before ``t_query``."""
    i = int(torch.searchsorted(t_us, torch.tensor(t_query), right=True)) - 1
    if i < 0:
        raise ValueError(f"no pose at or before {t_query} us")
    _, cm, deg = errors(seq, axis, t_us[i:i + 1], poses[i:i + 1])
    return float(cm[0]), float(deg[0])


def first_within(seq: Sequence, axis, t_us: torch.Tensor, poses: torch.Tensor, t_from: int, t_to: int,
                 max_cm: float, max_deg: float) -> int | None:
    """Microseconds from ``t_from`` to the first pose in ``[t_from, t_to]`` whose :func:`errors` are within
    ``max_cm`` and ``max_deg``, or ``None`` if none is."""
    sel = (t_us >= t_from) & (t_us <= t_to)
    if not bool(sel.any()):
        return None
    t, cm, deg = errors(seq, axis, t_us[sel], poses[sel])
    ok = (cm <= max_cm) & (deg <= max_deg)
    return None if not bool(ok.any()) else int(t[int(ok.nonzero()[0, 0])]) - t_from


def trial_batch(path, mode: str, args, cfg: TrackerConfig) -> tuple[list[dict], tuple[float, float] | None]:
    """Track one sequence's draws as a batch: one record per draw, and the error at the judged instant of the
    reference element: started at the truth (start mode) or tracking without the gap (blackout mode); ``None`` in
    away mode (no reference)."""
    seq = Sequence.load(path)
    t0 = int(seq.gt_t_us[0])
    if mode == "start":
        draws = args.draws
        gen = torch.Generator().manual_seed(args.seed)
        starts = torch.stack([perturb_pose(seq.gt_poses[0], args.offset_mm / 1e3, math.radians(args.offset_deg), gen)
                              for _ in range(draws)] + [seq.gt_poses[0]])  # the last: the reference from the truth
        streams = [seq.events] * (draws + 1)
        t_before, t_from, t_judge = None, t0, t0 + round(args.settle * 1e6)
    elif mode == "away":
        if "leave_view" not in seq.meta:
            raise SystemExit(f"{path.name}: not a sequence made with synth --leave-view")
        draws, starts, streams = 1, seq.gt_poses[:1], [seq.events]
        leave = seq.meta["leave_view"]
        t_before = t0 + round(leave["start_s"] * 1e6)
        t_from = t0 + round(back_on_path_s(leave["start_s"], leave["away_s"]) * 1e6)
        t_judge = t_from + round(args.settle * 1e6)
    else:
        draws = 1
        starts = seq.gt_poses[:1].repeat(2, 1)  # the second: the reference, without the gap
        gap0 = t0 + round(args.at * 1e6)
        gap1 = gap0 + round(args.gap_ms * 1e3)
        streams = [seq.events.select((seq.events.t < gap0) | (seq.events.t >= gap1)), seq.events]
        t_before, t_from, t_judge = gap0, gap1, gap1 + round(args.settle * 1e6)
        ends = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([gap0, gap1]))
        moved_cm = float((ends[1, :3] - ends[0, :3]).norm()) * 100.0
    t_end = min(int(seq.gt_t_us[-1]), t_judge + cfg.period_us)
    if t_judge > int(seq.gt_t_us[-1]):
        raise SystemExit(f"{path.name}: the sequence ends before the judged instant ({t_judge / 1e6:.3f} s)")
    B = starts.shape[0]
    tracker = EventPoseTracker(seq.camera, [str(path / "mesh.ply")] * B, cfg.replace(loss={"enabled": True}))
    try:
        times, poses, lost = tracker.track(streams, starts, t_start_us=t0, t_end_us=t_end,
                                           return_lost=True, progress=False)
    finally:
        tracker.close()
    axis, out = hidden_symmetry_axis(seq.mesh), []
    for b in range(draws):
        rec = {"sequence": path.name, "draw": b}
        if t_before is not None:
            rec["before"] = error_at(seq, axis, times[b], poses[b], t_before)
        if mode == "blackout":
            rec["moved_cm"] = moved_cm
        rec["after"] = error_at(seq, axis, times[b], poses[b], t_judge)
        rec["reached_us"] = first_within(seq, axis, times[b], poses[b], t_from, t_judge, args.max_cm, args.max_deg)
        rec["lost_flags"] = int(lost[b].sum())
        out.append(rec)
    truth = None if draws == B else error_at(seq, axis, times[draws], poses[draws], t_judge)
    return out, truth


def within(e: tuple[float, float], args) -> bool:
    return e[0] <= args.max_cm and e[1] <= args.max_deg


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("benchdir")
    ap.add_argument("--mode", choices=("start", "blackout", "away"), required=True)
    ap.add_argument("--only", default=None, help="comma-separated sequence names")
    ap.add_argument("--draws", type=int, default=5, help="start mode: start draws per sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--offset-mm", type=float, default=20.0)
    ap.add_argument("--offset-deg", type=float, default=10.0)
    ap.add_argument("--at", type=float, default=0.3, help="blackout mode: the gap's start (s after the first pose)")
    ap.add_argument("--gap-ms", type=float, default=200.0)
    ap.add_argument("--settle", type=float, default=None,
                    help="seconds after the start (start mode, default 0.2), after the gap (blackout, default 0.1) "
                    "or after the object is back in view (away, default 0.2)")
    ap.add_argument("--max-cm", type=float, default=1.0)
    ap.add_argument("--max-deg", type=float, default=5.0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    if args.draws < 1 or args.gap_ms < 0 or args.at < 0 or (args.settle is not None and args.settle < 0):
        ap.error("--draws must be >= 1 and --at, --gap-ms, --settle >= 0")
    if args.settle is None:
        args.settle = 0.1 if args.mode == "blackout" else 0.2
    cfg = TrackerConfig().override(args.set)
    paths = find_sequences(args.benchdir, None if args.only is None else args.only.split(","))
    records, truth_ok = [], []
    for path in paths:
        trials, truth = trial_batch(path, args.mode, args, cfg)
        for r in trials:
            records.append(r)
            moved = f"  moved {r['moved_cm']:5.1f} cm" if "moved_cm" in r else ""
            before = "" if "before" not in r else f"{moved}  before {r['before'][0]:6.2f} cm {r['before'][1]:6.2f} deg"
            reached = "never" if r["reached_us"] is None else f"{r['reached_us'] / 1e3:5.0f} ms"
            verdict = "ok" if within(r["after"], args) else "MISS"
            print(f"{r['sequence']:34s} {r['draw']:2d}{before}  after {r['after'][0]:6.2f} cm {r['after'][1]:6.2f} deg"
                  f"  reached {reached}  lost flags {r['lost_flags']:4d}  {verdict}", flush=True)
        if truth is None:
            continue
        truth_ok.append(within(truth, args))
        for r in trials:
            r["reference_ok"] = truth_ok[-1]
        label = "from the truth " if args.mode == "start" else "without the gap"
        print(f"{path.name:34s} {label}  after {truth[0]:6.2f} cm {truth[1]:6.2f} deg  "
              f"{'ok' if truth_ok[-1] else 'MISS'}", flush=True)
    counted = [r for r in records if "before" not in r or within(r["before"], args)]
    ok = sum(within(r["after"], args) for r in counted)
    print(f"{args.mode}: {ok} of {len(counted)} within {args.max_cm} cm / {args.max_deg} deg "
          f"({len(records) - len(counted)} trials off before {'it left' if args.mode == 'away' else 'the gap'}, not "
          f"counted); "
          f"{sum(r['reached_us'] is not None for r in counted)} of {len(counted)} reached them by then")
    if args.mode == "start":
        print(f"started at the truth: {sum(truth_ok)} of {len(truth_ok)} sequences within them at that instant")
    elif args.mode == "blackout":
        misses = [r for r in counted if not within(r["after"], args)]
        print(f"without the gap: {sum(r['reference_ok'] for r in counted)} of {len(counted)} counted trials within "
              f"them at that instant; {sum(not r['reference_ok'] for r in misses)} of the {len(misses)} misses miss "
              f"without the gap too (the tracker's own error)")
        spec = [r for r in counted if r["moved_cm"] <= MAX_MOVED_CM]
        print(f"blackout, the object moving at most {MAX_MOVED_CM:g} cm in the gap (issue 25's trials): "
              f"{sum(within(r['after'], args) for r in spec)} of {len(spec)}")


if __name__ == "__main__":
    main()
