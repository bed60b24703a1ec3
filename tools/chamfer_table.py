"""Is the truth the best pose under the chamfer cost, and under the template score? A table over offsets.

For each sequence directory and time, feeds the events of the last 0.1 s into an EROS and a time surface (the
tracker's defaults), then scores the true pose and the true pose moved by fixed offsets (translations along each
camera axis, both signs; rotations about each camera axis through the object origin, both signs; and random
combinations) with

- the chamfer cost (:mod:`torchevtrack.chamfer`, full resolution, recent events within ``--window-ms``,
  a fixed region around the truth), lower better;
- the tracker's template score (its template of the pose's render against the EROS observation), higher better.

Prints per offset magnitude how often the truth beats the offset pose under each score, and the worst margin.

    python tools/chamfer_table.py SEQDIR [SEQDIR ...] [--at 0.3 0.9 1.5] [--window-ms 10]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from torchevtrack.chamfer import chamfer, distance_map, model_edges, recent_events
from torchevtrack.config import TrackerConfig
from torchevtrack.geometry import quat_exp, quat_mul
from torchevtrack.raster import RasterRenderer
from torchevtrack.stages.eros import EROS, TimeSurface
from torchevtrack.stages.eros import canvas_observation
from torchevtrack.stages.template import template_model
from torchevtrack.synth.sequence import Sequence


def moved(pose: torch.Tensor, dt: np.ndarray, dr: np.ndarray) -> torch.Tensor:
    out = pose.clone()
    out[:3] += torch.as_tensor(dt, dtype=torch.float64)
    out[3:] = quat_mul(quat_exp(torch.as_tensor(dr, dtype=torch.float64)), pose[3:])
    return out


def offsets(rng: np.random.Generator):
    """(label, dt (m), dr (rad)) of the offsets scored."""
    out = []
    for cm in (1, 2, 4, 8):
        for ax in range(3):
            for sg in (-1, 1):
                dt = np.zeros(3)
                dt[ax] = sg * cm / 100
                out.append((f"t {cm} cm", dt, np.zeros(3)))
    for deg in (5, 10, 20, 30):
        for ax in range(3):
            for sg in (-1, 1):
                dr = np.zeros(3)
                dr[ax] = sg * math.radians(deg)
                out.append((f"r {deg} deg", np.zeros(3), dr))
    for cm, deg in ((2, 10), (5, 20)):
        for _ in range(12):
            u, w = rng.normal(size=3), rng.normal(size=3)
            out.append((f"{cm} cm+{deg} deg", cm / 100 * u / np.linalg.norm(u),
                        math.radians(deg) * w / np.linalg.norm(w)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdirs", nargs="+")
    ap.add_argument("--at", type=float, nargs="+", default=[0.3, 0.9, 1.5])
    ap.add_argument("--window-ms", type=float, default=10.0)
    ap.add_argument("--cap", type=float, default=20.0, help="distance cap (pixels)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = TrackerConfig()
    tally: dict[str, list] = {}
    for seqdir in args.seqdirs:
        seq = Sequence.load(seqdir)
        cam, ev = seq.camera, seq.events
        renderer = RasterRenderer(seq.mesh, cam)
        radius = float(torch.as_tensor(seq.mesh.vertices).norm(dim=1).max())
        for at in args.at:
            t_now = int(seq.gt_t_us[0]) + round(at * 1e6)
            n = int(torch.searchsorted(ev.t, torch.tensor(t_now)))
            a = max(0, int(torch.searchsorted(ev.t, torch.tensor(t_now - 100_000))))
            eros = EROS(cam.height, cam.width, cfg.eros.kernel_size, cfg.eros.decay)
            ts = TimeSurface(cam.height, cam.width)
            eros(ev.x[a:n], ev.y[a:n])
            ts(ev.x[a:n], ev.y[a:n], ev.t[a:n])
            k = int(torch.searchsorted(seq.gt_t_us, torch.tensor(t_now)).clamp(max=len(seq.gt_t_us) - 1))
            truth = seq.gt_poses[k]
            events = recent_events(ts.last_us[0], t_now, round(args.window_ms * 1000), min_support=1)
            z = float(truth[2])
            uc, vc = cam.fx * float(truth[0]) / z + cam.cx, cam.fy * float(truth[1]) / z + cam.cy
            half = cam.fx * (radius + 0.1) / (z - 0.1 - radius)
            u0, v0 = max(0, int(uc - half)), max(0, int(vc - half))
            u1, v1 = min(cam.width, int(uc + half)), min(cam.height, int(vc + half))
            roi = (u0, v0, u1 - u0, v1 - v0)
            ev_roi = events[v0:v1, u0:u1]
            dmap = distance_map(ev_roi, args.cap)

            def cost(p):
                r = renderer.render(p[None], roi=roi)
                return chamfer(model_edges(r.depth[0].numpy(), r.gray[0].numpy()), ev_roi, dmap, args.cap)

            def tscore(p):
                r = renderer.render(p[None])
                model = template_model(p[None], r.depth, r.gray, (0, 0), cam, canvas=cfg.template.canvas,
                                       margin_px=cfg.template.margin_px)
                o = canvas_observation(eros.surface, ts.last_us[:, None], model.box, cfg.template.canvas,
                                       torch.tensor([t_now]), cfg.eros.max_age_us, cfg.eros.recency_us)
                return float(model.fit_canvas(o.reshape(1, -1)).s0[0])

            c0, s0 = cost(truth), tscore(truth)
            rng = np.random.default_rng(int(at * 1000))
            for label, dt, dr in offsets(rng):
                p = moved(truth, dt, dr)
                c, s = cost(p), tscore(p)
                tally.setdefault(label, []).append((c - c0, s0 - s))
                if c <= c0:
                    print(f"  truth not best: {label} dt {np.round(dt * 100, 1)} cm dr {np.round(np.degrees(dr))} deg:"
                          f" {c:.2f} <= {c0:.2f}")
            print(f"{seqdir} at {at} s: {int(ev_roi.sum())} recent event pixels, truth chamfer {c0:.2f} px, "
                  f"template {s0:.2f}", flush=True)
    print("\n| offset | poses | truth best (chamfer) | worst chamfer margin (px) | truth best (template) |")
    print("| --- | --- | --- | --- | --- |")
    for label, v in tally.items():
        v = np.array(v)
        print(f"| {label} | {len(v)} | {100 * np.mean(v[:, 0] > 0):.0f} % | {v[:, 0].min():+.2f} | "
              f"{100 * np.mean(v[:, 1] > 0):.0f} % |")


if __name__ == "__main__":
    main()
