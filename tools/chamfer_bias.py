"""Where is the chamfer cost's minimum near the truth? Polish from the true pose and print the offset per axis.

A correction that pulls the pose towards the chamfer minimum (e.g. a depth / pitch correction in tracking) can only
stop drift if that minimum lies at the truth. For each sequence and time this feeds the last 0.1 s of events into a
time surface, runs :class:`~torchevtrack.stages.relocalise.Relocaliser` with no search (one level without offsets,
shifts of at most a few pixels) from the true pose, so only its Gauss-Newton polish moves it, and prints the result's
offset from the truth: translation per camera axis (cm, z = depth) and rotation per camera axis (deg).

    python tools/chamfer_bias.py SEQDIR [SEQDIR ...] [--at 0.2 0.4 ...]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from torchevtrack.geometry import quat_conj, quat_log, quat_mul
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.eros import TimeSurface
from torchevtrack.stages.relocalise import Level, Relocaliser
from torchevtrack.synth.sequence import Sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdirs", nargs="+")
    ap.add_argument("--at", type=float, nargs="+", default=[0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8])
    args = ap.parse_args()
    torch.set_num_threads(1)
    for seqdir in args.seqdirs:
        seq = Sequence.load(seqdir)
        cam, ev = seq.camera, seq.events
        radius = float(torch.as_tensor(seq.mesh.vertices).norm(dim=1).max())
        reloc = Relocaliser(RasterRenderer(seq.mesh, cam), radius, levels=(Level(0.0, (0.0,), 0.003, 1.0),),
                            beam=1, max_seeds=1, polish_steps=30, kick_deg=0.0)
        offsets = []
        for at in args.at:
            t_now = int(seq.gt_t_us[0]) + round(at * 1e6)
            n = int(torch.searchsorted(ev.t, torch.tensor(t_now)))
            a = max(0, int(torch.searchsorted(ev.t, torch.tensor(t_now - 100_000))))
            ts = TimeSurface(cam.height, cam.width)
            ts(ev.x[a:n], ev.y[a:n], ev.t[a:n])
            k = int(torch.searchsorted(seq.gt_t_us, torch.tensor(t_now)).clamp(max=len(seq.gt_t_us) - 1))
            truth = seq.gt_poses[k].double()
            out = reloc(truth[None], ts.last_us, torch.tensor([t_now]))
            dt = (out.pose[0, :3] - truth[:3]).numpy() * 100
            dr = np.degrees(quat_log(quat_mul(out.pose[0, 3:], quat_conj(truth[3:]))).numpy())
            offsets.append(np.concatenate((dt, dr)))
            print(f"{seqdir} at {at} s: dt {np.round(dt, 2)} cm, dr {np.round(dr, 1)} deg, cost "
                  f"{float(out.cost[0]):.2f}", flush=True)
        o = np.array(offsets)
        print(f"{seqdir}: mean dt {np.round(o[:, :3].mean(0), 2)} cm (|dz| {np.abs(o[:, 2]).mean():.2f}), "
              f"mean |dr| {np.round(np.abs(o[:, 3:]).mean(0), 1)} deg")


if __name__ == "__main__":
    main()
