"""Which stage loses a split? Each sequence tracked from its true first pose with the velocity as estimated and
with the true twist in its place.

Three modes per sequence (``--modes``, default all three), one tracker at a time, one worker, no pipeline thread:

* ``estimated``: the tracker as configured (``--config`` / ``--set``).
* ``true-twist``: after every update the velocity filter's state is set to the ground-truth twist of the coming
  window (the constant twist between the true poses at its ends, about the object centre), with ``velocity.rho = 1``,
  the flow ignored (``velocity.r_px = 1e6``) and no correction feedback, so the next propagation moves the pose by
  the true motion exactly. What the run then loses, the correction and the UKF lose.
* ``true-twist-only``: the same without the correction (``template.enabled = false``): pure integration of the
  true twist, a check that the oracle itself holds (errors of a few millimetres over a second).

Prints, per sequence and mode, the translation RMSE (cm), the RMSE of its depth component and of its lateral
component (camera frame, cm), the rotation RMSE (deg, symmetry axis left out) and whether the EDOPT rule failed
the run; then per mode the runs held. ``--json`` writes the table, with the mean signed depth error
(``depth_mean_cm``, positive: too far).

    python tools/oracle_split.py data/wide_dev1 --duration 1.0 [--modes estimated,true-twist] [--set k=v ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from torchevtrack.benchmark import find_sequences
from torchevtrack.config import TrackerConfig
from torchevtrack.mesh import hidden_symmetry_axis
from torchevtrack.metrics import evaluate, mesh_points, sym_failed, sym_rmse_r_deg
from torchevtrack.stages.propagate import twist_between
from torchevtrack.stages.velocity import shift_twist
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker

MODES = ("estimated", "true-twist", "true-twist-only")
TRUE_TWIST = ["velocity.rho=1.0", "velocity.r_px=1000000.0", "velocity.feedback_gain=0.0"]


def window_twist(gt_t: torch.Tensor, gt: torch.Tensor, t_us: int, period_us: int) -> torch.Tensor:
    """The constant twist ``(1, 6)`` about the object centre that moves the true pose at ``t_us`` to the one at
    ``t_us + period_us`` (nearest ground-truth samples; the synthetic ground truth is sampled at the update rate)."""
    k = torch.searchsorted(gt_t, torch.tensor([t_us, t_us + period_us])).clamp(0, len(gt_t) - 1)
    dt = torch.tensor([max(int(gt_t[k[1]] - gt_t[k[0]]), 1) * 1e-6], dtype=torch.float64)
    return shift_twist(twist_between(gt[k[0]][None], gt[k[1]][None], dt), gt[k[0]][None, :3])


def track(seq: Sequence, cfg: TrackerConfig, duration_s: float, true_twist: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses ``(N, 7)`` at update times ``(N,)`` us of the first ``duration_s`` seconds, from the true first pose."""
    tracker = EventPoseTracker(seq.camera, seq.mesh, cfg, workers=1, pipeline=False)
    gt_t, gt = seq.gt_t_us, seq.gt_poses
    ev, t0, period = seq.events, int(gt_t[0]), tracker.period_us
    n = min(round(duration_s * 1e6), int(gt_t[-1]) - t0) // period
    bounds = torch.searchsorted(ev.t, t0 + torch.arange(n + 1) * period)
    times, poses = t0 + period * torch.arange(1, n + 1), []
    try:
        tracker.reset(gt[0])
        for i in range(n):
            if true_twist:  # the twist of the coming window: the propagation follows the truth
                tracker.velocity.x.copy_(window_twist(gt_t, gt, int(times[i]) - period, period).to(tracker.velocity.x.dtype))
            a, b = int(bounds[i]), int(bounds[i + 1])
            poses.append(tracker(ev.x[a:b], ev.y[a:b], ev.t[a:b], ev.p[a:b], t_us=int(times[i]))[0].clone())
    finally:
        tracker.close()
    return times, torch.stack(poses)


def errors(seq: Sequence, times: torch.Tensor, poses: torch.Tensor) -> dict:
    """RMSE (cm, deg), the depth and lateral parts of the translation error, and the EDOPT rule's verdict."""
    axis = hidden_symmetry_axis(seq.mesh)
    m = evaluate(times, poses, seq.gt_t_us, seq.gt_poses, mesh_points=mesh_points(seq.mesh.vertices),
                 symmetry_axis=None if axis is None else torch.as_tensor(axis))
    g = seq.gt_poses[torch.searchsorted(seq.gt_t_us, times).clamp(0, len(seq.gt_t_us) - 1)]
    d = (poses[:, :3] - g[:, :3]) * 100
    return {"rmse_t_cm": m["rmse_t_cm"], "depth_cm": float(d[:, 2].square().mean().sqrt()),
            "depth_mean_cm": float(d[:, 2].mean()),
            "lateral_cm": float(d[:, :2].square().sum(1).mean().sqrt()),
            "rmse_r_deg": sym_rmse_r_deg(m), "failed": sym_failed(m)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench_dir", help="a directory of sequence directories (a benchmark or a wide-suite split)")
    ap.add_argument("--duration", type=float, default=1.0, help="seconds tracked per sequence")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of {','.join(MODES)}")
    ap.add_argument("--config", help="tracker config YAML (default: the defaults)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config change (repeatable)")
    ap.add_argument("--json", help="write the per-sequence results here")
    args = ap.parse_args()
    modes = args.modes.split(",")
    if bad := [m for m in modes if m not in MODES]:
        ap.error(f"unknown mode(s) {bad}; choose from {MODES}")
    torch.set_num_threads(1)
    base = (TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()).override(args.set)
    cfgs = {"estimated": base, "true-twist": base.override(TRUE_TWIST),
            "true-twist-only": base.override(TRUE_TWIST + ["template.enabled=false"])}
    results: dict[str, dict] = {m: {} for m in modes}
    print(f"{'sequence':30s} " + " ".join(f"{m + ': t / z / xy cm, deg':>36s}" for m in modes))
    for path in find_sequences(args.bench_dir):
        seq = Sequence.load(path)
        cells = []
        for m in modes:
            r = results[m][path.name] = errors(seq, *track(seq, cfgs[m], args.duration, m != "estimated"))
            cells.append(f"{r['rmse_t_cm']:7.2f} {r['depth_cm']:7.2f} {r['lateral_cm']:6.2f} {r['rmse_r_deg']:6.1f}"
                         f" {'lost' if r['failed'] else 'held':>5s}")
        print(f"{path.name:30s} " + " ".join(f"{c:>36s}" for c in cells), flush=True)
    for m in modes:
        v = list(results[m].values())
        print(f"{m}: {sum(not r['failed'] for r in v)} of {len(v)} held; mean {statistics.mean(r['rmse_t_cm'] for r in v):.2f}"
              f" cm (depth {statistics.mean(r['depth_cm'] for r in v):.2f}, lateral "
              f"{statistics.mean(r['lateral_cm'] for r in v):.2f}), median "
              f"{statistics.median(r['rmse_t_cm'] for r in v):.2f} cm")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
