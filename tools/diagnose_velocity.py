"""How good is the flow velocity? The tracker's twist from flow against the ground-truth twist.

Runs the tracker on the first seconds of a sequence directory and, after every update, compares the
velocity filter's state (the twist about the object centre, ``[c_dot, w]``) with the ground truth
(finite differences of ``gt_poses.txt`` at the middle of the window, converted to the same centre
form). Prints per component the least-squares slope of estimate on truth, their correlation and the
RMS errors, then the pose errors of the run.

With ``--oracle`` the filter's state is replaced by the ground truth after each update (the flow is still
computed and compared): the pose errors then show what the rest of the pipeline does with a perfect
velocity. The comparison then flatters the flow: the filter's prior is ``rho`` times the truth.

    .venv/bin/python tools/diagnose_velocity.py data/bench/mustard_fast --duration 0.5 [--oracle]
"""

from __future__ import annotations

import argparse
import math

import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.metrics import per_pose_errors, twists_from_poses
from torchevtrack.stages.velocity import VelocityKF, shift_twist
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker

AXES = ("vx", "vy", "vz", "wx", "wy", "wz")


class OracleVelocityKF(VelocityKF):
    """A :class:`VelocityKF` that, after each flow update, records its estimate and the truth ``truth()``
    ``(B, 6)`` (centre form); with ``replace`` it then continues from the truth (covariance ``1e-8 I``)."""

    def __init__(self, base: VelocityKF, truth, replace: bool) -> None:
        super().__init__(base.camera, rho=base.rho, r_px=base.r_px, min_vectors=base.min_vectors,
                         iters=base.iters, k=base.k, normal=base.normal, batch_size=base.batch_size)
        self.load_state_dict(base.state_dict())
        self.truth, self.replace = truth, replace
        self.log: list[tuple[torch.Tensor, torch.Tensor]] = []

    def update(self, uv, flow, depth, valid, dt, centre=None):
        out = super().update(uv, flow, depth, valid, dt, centre=centre)
        ref = self.truth()
        self.log.append((self.x.clone(), ref))
        if self.replace:
            self.x.copy_(ref)
            self.P.copy_(torch.eye(6, dtype=self.P.dtype) * 1e-8)
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir")
    ap.add_argument("--duration", type=float, default=0.5, help="seconds tracked from the first pose")
    ap.add_argument("--oracle", action="store_true", help="continue from the true twist after every update")
    ap.add_argument("--config", help="tracker config YAML (default: the defaults)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    seq = Sequence.load(args.seqdir)
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    if cfg.velocity.source != "flow":
        raise SystemExit("the config must take the velocity from flow (velocity.source: flow)")
    tracker = EventPoseTracker(seq.camera, seq.mesh, cfg)
    gt_t, gt = seq.gt_t_us, seq.gt_poses
    gt_twist = twists_from_poses(gt_t, gt)

    def truth() -> torch.Tensor:
        k = int(torch.searchsorted(gt_t, tracker.t_last[0] - tracker.period_us // 2).clamp(0, len(gt_t) - 1))
        return shift_twist(gt_twist[k:k + 1], gt[k:k + 1, :3])

    oracle = OracleVelocityKF(tracker.velocity, truth, args.oracle)
    tracker.velocity = oracle
    t0 = int(gt_t[0])
    times, poses = tracker.track(seq.events, gt[0], t_start_us=t0, t_end_us=t0 + round(args.duration * 1e6))
    tracker.close()

    est = torch.stack([e for e, _ in oracle.log])[:, 0]
    ref = torch.stack([r for _, r in oracle.log])[:, 0]
    de, dr = est - est.mean(0), ref - ref.mean(0)
    slope = (est * ref).sum(0) / (ref * ref).sum(0)
    corr = (de * dr).sum(0) / (de.norm(dim=0) * dr.norm(dim=0)).clamp_min(1e-30)
    print(f"{len(oracle.log)} flow updates of {args.seqdir}" + (" (oracle velocity)" if args.oracle else ""))
    print("component  slope  corr   rms err  rms true")
    for i, a in enumerate(AXES):
        err = (est[:, i] - ref[:, i]).square().mean().sqrt()
        print(f"{a:>9s}  {float(slope[i]):5.2f}  {float(corr[i]):5.2f}  {float(err):7.3f}  {float(ref[:, i].square().mean().sqrt()):7.3f}")
    e = per_pose_errors(times[0], poses[0], gt_t, gt)
    print(f"pose RMSE {float(e['te'].square().mean().sqrt()) * 100:.2f} cm / "
          f"{math.degrees(float(e['re'].square().mean().sqrt())):.2f} deg")


if __name__ == "__main__":
    main()
