"""Does the re-localiser find the object from a pose far off, and what does a call cost?

Feeds a sequence's events up to ``--at`` seconds into a time surface, then
calls :class:`~torchevtrack.stages.relocalise.Relocaliser` from the true pose at that time moved by ``--dt-cm`` in
a random direction and turned by ``--dr-deg`` about a random axis, ``--trials`` times, and prints each result's
error against the truth, its clear flag and the call's time.

    python tools/bench_relocalise.py SEQDIR [SEQDIR ...] [--at 0.3 ...] [--dt-cm 5] [--dr-deg 20] [--trials 5]
        [--decimate FACES]
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from torchevtrack.geometry import quat_conj, quat_exp, quat_log, quat_mul
from torchevtrack.mesh import load_mesh
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.eros import TimeSurface
from torchevtrack.stages.relocalise import Relocaliser
from torchevtrack.synth.sequence import Sequence


def perturb(pose: torch.Tensor, dt_m: float, dr_rad: float, gen: torch.Generator) -> torch.Tensor:
    """``pose`` ``(7,)`` moved by ``dt_m`` and turned by ``dr_rad`` (about its origin) in random directions."""
    u = torch.randn(3, generator=gen, dtype=torch.float64)
    w = torch.randn(3, generator=gen, dtype=torch.float64)
    out = pose.clone()
    out[:3] += dt_m * u / u.norm()
    out[3:] = quat_mul(quat_exp(dr_rad * w / w.norm()), pose[3:])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdirs", nargs="+")
    ap.add_argument("--at", type=float, nargs="+", default=[0.3], help="seconds after the first pose")
    ap.add_argument("--dt-cm", type=float, default=5.0)
    ap.add_argument("--dr-deg", type=float, default=20.0)
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--decimate", type=int, help="render a mesh decimated to about this many faces")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []  # (found, clear, ms)
    for seqdir in args.seqdirs:
        seq = Sequence.load(seqdir)
        cam, ev = seq.camera, seq.events
        radius = float(torch.as_tensor(seq.mesh.vertices).norm(dim=1).max())
        mesh = seq.mesh if args.decimate is None else load_mesh(seq.mesh, decimate=args.decimate)
        reloc = Relocaliser(RasterRenderer(mesh, cam), radius)
        gen = torch.Generator().manual_seed(args.seed)
        for at in args.at:
            t_now = int(seq.gt_t_us[0]) + round(at * 1e6)
            n = int(torch.searchsorted(ev.t, torch.tensor(t_now)))
            ts = TimeSurface(cam.height, cam.width)
            a = max(0, int(torch.searchsorted(ev.t, torch.tensor(t_now - 100_000))))  # the last 0.1 s suffice
            ts(ev.x[a:n], ev.y[a:n], ev.t[a:n])
            k = int(torch.searchsorted(seq.gt_t_us, torch.tensor(t_now)).clamp(max=len(seq.gt_t_us) - 1))
            truth = seq.gt_poses[k]
            t_arg = torch.tensor([t_now])
            reloc(truth[None], ts.last_us, t_arg)  # compile
            for i in range(args.trials):
                start = perturb(truth, args.dt_cm / 100, math.radians(args.dr_deg), gen)
                t0 = time.perf_counter()
                out = reloc(start[None], ts.last_us, t_arg)
                ms = (time.perf_counter() - t0) * 1e3
                te = float((out.pose[0, :3] - truth[:3]).norm()) * 100
                re = math.degrees(float(quat_log(quat_mul(out.pose[0, 3:], quat_conj(truth[3:]))).norm()))
                rows.append((te <= 1 and re <= 5, bool(out.clear[0]), ms))
                print(f"{seqdir} at {at} s, trial {i}: error {te:.2f} cm / {re:.2f} deg, cost "
                      f"{float(out.cost[0]):.2f}, runner-up {float(out.runner_up[0]):.2f}, clear {bool(out.clear[0])}, "
                      f"{ms:.0f} ms", flush=True)
    found = [r[0] for r in rows]
    clear = [r for r in rows if r[1]]
    print(f"{sum(found)} of {len(rows)} within 1 cm / 5 deg; clear {len(clear)}, of which right "
          f"{sum(r[0] for r in clear)}; right but not clear {sum(r[0] and not r[1] for r in rows)}; "
          f"median {sorted(r[2] for r in rows)[len(rows) // 2]:.0f} ms per call")


if __name__ == "__main__":
    main()
