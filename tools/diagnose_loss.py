"""Why is an object lost? Per-update errors by axis, the tracker's quality, and the template score at the truth.

Runs the tracker (one worker, no pipeline thread, so its surfaces are settled after each update) on the first
seconds of a sequence directory and after every ``--every``-th update prints: the translation error per camera
axis (cm), the rotation error per camera axis (deg; rx = pitch, ry = yaw, rz = roll), the events of the window, the
flow vectors the velocity filter used, the tracker's template score, and the template score of the **ground-truth
pose** against the same EROS observation (its own render and template). When the truth scores clearly higher than
the estimate, the observation still holds the object and the search did not reach it (basin/reach); when it does
not, the observation itself is poor (noise, too few or blurred events). ``--oracle-velocity`` sets the velocity
filter's state to the true twist of the coming window after each update, with the flow and the feedback switched off
(``tools/oracle_split.py``'s ``true-twist`` mode), so the propagation follows the truth exactly.

``--twist`` prints, in place of the score columns, the velocity filter's twist about the object centre (the state
``x``, cm/s and deg/s) beside the true twist of the window, and at the end their RMS differences per axis.

    python tools/diagnose_loss.py SEQDIR --duration 0.5 --every 10 [--twist] [--oracle-velocity] [--config FILE]
"""

from __future__ import annotations

import argparse
import math

import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.geometry import quat_conj, quat_log, quat_mul
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.eros import canvas_observation
from torchevtrack.stages.template import area_weight, template_model
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker

from oracle_split import TRUE_TWIST, window_twist


def interpolate_gt(gt_t: torch.Tensor, gt: torch.Tensor, t: int) -> torch.Tensor:
    """Nearest ground-truth pose at ``t`` (the synthetic ground truth is dense: 1 kHz or more)."""
    k = int(torch.searchsorted(gt_t, torch.tensor(t)).clamp(0, len(gt_t) - 1))
    return gt[k]


def template_score(renderer: RasterRenderer, pose: torch.Tensor, tracker: EventPoseTracker, t_now: int,
                   cfg: TrackerConfig, recency_us: torch.Tensor) -> float:
    """Template score of ``pose`` ``(7,)`` against the tracker's current EROS observation (own render, canvas),
    weighed with the recency window ``(1,)`` us the tracker's last update observed with: the tracker's own score
    (its template with the interior, less the area term), so the two columns compare."""
    r = renderer.render(pose[None])
    if not bool((r.depth > 0).any()):
        return float("nan")
    t = cfg.template
    model = template_model(pose[None].double(), r.depth, r.gray, (0, 0), tracker.camera, canvas=t.canvas,
                           margin_px=t.margin_px, interior=t.interior)
    times = tracker.flow.sae if tracker.time_surface is None else tracker.time_surface.last_us[:, None]
    obs = canvas_observation(tracker.eros.surface, times, model.box,
                             t.canvas, torch.tensor([t_now]), cfg.eros.max_age_us, recency_us).reshape(1, -1)
    area = area_weight(obs[0].numpy(), model.valid[0].numpy(), t.canvas, t.interior)
    return float(model.fit_canvas(obs).s0[0]) - area


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir")
    ap.add_argument("--duration", type=float, default=0.5, help="seconds tracked from the first pose")
    ap.add_argument("--every", type=int, default=10, help="print every N-th update")
    ap.add_argument("--config", help="tracker config YAML (default: the defaults)")
    ap.add_argument("--oracle-velocity", action="store_true", help="continue from the true twist after each update")
    ap.add_argument("--twist", action="store_true",
                    help="print the velocity filter's twist about the centre and the true one instead of the score "
                         "columns (cm/s, deg/s), and their RMS differences at the end")
    args = ap.parse_args()
    torch.set_num_threads(1)

    seq = Sequence.load(args.seqdir)
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    if args.oracle_velocity:
        cfg = cfg.override(TRUE_TWIST)
    tracker = EventPoseTracker(seq.camera, seq.mesh, cfg, workers=1, pipeline=False)
    renderer = RasterRenderer(seq.mesh, seq.camera)
    gt_t, gt = seq.gt_t_us, seq.gt_poses
    ev = seq.events
    t0, period = int(gt_t[0]), tracker.period_us
    n = int(args.duration * 1e6) // period
    bounds = torch.searchsorted(ev.t, t0 + torch.arange(n + 1) * period)
    tracker.reset(gt[0])
    print(f"{args.seqdir}: {len(ev)} events, {ev.event_rate() / 1e6:.2f} M/s")
    twist_names = [f"{q}{axis}_{k}" for q in "vw" for k in ("est", "gt") for axis in "xyz"]
    columns = "".join(f" {c:>7s}" for c in twist_names) if args.twist else "  events flow  score  score@gt"
    print("   t_ms  dx_cm  dy_cm  dz_cm  rx_deg ry_deg rz_deg" + columns + "  te_cm re_deg")
    first_fail = None
    twist_errors = []
    scale = torch.tensor([100.0] * 3 + [180.0 / math.pi] * 3, dtype=torch.float64)  # m/s, rad/s -> cm/s, deg/s
    for i in range(n):
        a, b = int(bounds[i]), int(bounds[i + 1])
        t_now = t0 + (i + 1) * period
        window = tracker.recency.window_us  # the update sets the next one: this is the window it observes with
        if args.oracle_velocity or args.twist:  # about the centre, as the filter's state
            true_twist = window_twist(gt_t, gt, t_now - period, period)[0]
        if args.oracle_velocity:  # the twist of this window: the propagation follows the truth
            tracker.velocity.x.copy_(true_twist[None].to(tracker.velocity.x.dtype))
        pose = tracker(ev.x[a:b], ev.y[a:b], ev.t[a:b], ev.p[a:b], t_us=t_now)[0]
        if args.twist:
            est, true = tracker.velocity.x[0].double() * scale, true_twist.double() * scale
            twist_errors.append((est - true) ** 2)
        g = interpolate_gt(gt_t, gt, t_now)
        dt_cm = (pose[:3] - g[:3]) * 100
        rot = torch.rad2deg(quat_log(quat_mul(pose[3:], quat_conj(g[3:]))))
        te, re = float(dt_cm.norm()), float(rot.norm())
        if first_fail is None and (te > 7 or re > 40):
            first_fail = i
        if i % args.every == 0 or (first_fail == i):
            if args.twist:
                middle = "".join(f" {float(v):7.0f}" for v in torch.cat([est[:3], true[:3], est[3:], true[3:]]))
            else:
                q = tracker.quality
                s_gt = template_score(renderer, g, tracker, t_now, cfg, window)
                middle = f" {int(q.events[0]):7d} {int(q.flow_vectors[0]):4d} {float(q.score[0]):6.1f} {s_gt:8.1f}"
            print(f"{(t_now - t0) / 1000:7.1f} " + " ".join(f"{float(v):6.2f}" for v in dt_cm) + " "
                  + " ".join(f"{float(v):6.1f}" for v in rot) + middle
                  + f" {te:6.2f} {re:6.1f}" + ("  <- error > 7 cm / 40 deg" if first_fail == i else ""))
    tracker.close()
    if twist_errors:
        rms = torch.stack(twist_errors).mean(0).sqrt()
        print("RMS twist error, velocity filter against the truth: v " + " ".join(f"{float(v):.1f}" for v in rms[:3])
              + " cm/s, w " + " ".join(f"{float(v):.0f}" for v in rms[3:]) + " deg/s")


if __name__ == "__main__":
    main()
