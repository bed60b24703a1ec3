"""Milliseconds per render of the two render backends (pyrender, raster) on the tracker's hot path.

The object (default 006_mustard_bottle) is 0.5 m in front of the default 640x480 camera (fx = fy = 502.3),
turning a little between renders like a tracked object (a sweep of 64 poses, cycled). Each render is one
pose in a window around the object's projection: a ``--roi``-pixel square (default 160) and the window
the tracker would use (:func:`torchevtrack.stages.template.render_window`, bounding sphere + 24 px margin,
clipped to the frame). Full mesh and a ``--decimate``-face copy; shaded (depth + grey) and depth only.
Timing: 1 torch thread, best of ``--rounds`` rounds of ``--renders`` renders, after a warm-up (numba
compile or cache load, GL program upload).

    PYOPENGL_PLATFORM=egl .venv/bin/python tools/bench_render.py [--object can] [--decimate 4000] [--roi 160]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import torch  # noqa: E402

from torchevtrack.camera import Camera  # noqa: E402
from torchevtrack.geometry import quat_exp  # noqa: E402
from torchevtrack.mesh import load_mesh  # noqa: E402
from torchevtrack.render import BACKENDS, make_renderer  # noqa: E402
from torchevtrack.stages.template import render_window  # noqa: E402


def sweep(distance: float, n: int = 64) -> torch.Tensor:
    """``(n, 7)`` float64 poses ``distance`` metres ahead, turning by up to ~0.35 rad about a tilted axis."""
    s = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    rotvec = torch.stack((0.3 + 0.2 * torch.sin(6.3 * s), 0.35 * torch.sin(3.1 * s), 0.1 * torch.cos(4.0 * s)), -1)
    t = torch.stack((0.01 * torch.sin(5.0 * s), -0.01 * torch.cos(5.0 * s), torch.full_like(s, distance)), -1)
    return torch.cat((t, quat_exp(rotvec)), -1)


def windows(poses: torch.Tensor, camera: Camera, radius: float, size: int | None) -> list[tuple[int, int, int, int]]:
    """Per pose, a ``size`` square around the projected origin, or (``None``) the tracker's clipped window."""
    if size is None:
        win = render_window(poses, camera, radius)
        w, h = win[:, 2].clamp(max=camera.width), win[:, 3].clamp(max=camera.height)
        u = win[:, 0].clamp(min=0).minimum(camera.width - w)
        v = win[:, 1].clamp(min=0).minimum(camera.height - h)
        return [tuple(r) for r in torch.stack((u, v, w, h), -1).tolist()]
    uv = camera.project(poses[:, :3]).round().long() - size // 2
    return [(u, v, size, size) for u, v in uv.tolist()]


def ms_per_render(renderer, poses: torch.Tensor, rois, shaded: bool, renders: int, rounds: int) -> float:
    for b in range(len(poses)):  # warm-up: compile / upload, and every window size once
        renderer.render(poses[b], roi=rois[b], shaded=shaded)
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for i in range(renders):
            b = i % len(poses)
            renderer.render(poses[b], roi=rois[b], shaded=shaded)
        best = min(best, (time.perf_counter() - t0) / renders)
    return best * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="006_mustard_bottle")
    ap.add_argument("--decimate", type=int, default=4000, help="faces of the decimated mesh")
    ap.add_argument("--distance", type=float, default=0.5, help="metres")
    ap.add_argument("--roi", type=int, default=160, help="side of the square window, pixels")
    ap.add_argument("--renders", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    camera = Camera.default()
    poses = sweep(a.distance)
    print(f"{a.object} at {a.distance} m, {camera.width}x{camera.height} camera, 1 thread; ms per render "
          f"(best of {a.rounds} x {a.renders})")
    print(f"{'mesh':<14s}{'window':<20s}{'mode':<8s}" + "".join(f"{b:>10s}" for b in BACKENDS) + "   speed-up")
    for decimate in (None, a.decimate):
        mesh = load_mesh(a.object, decimate=decimate)
        radius = float(torch.as_tensor(mesh.vertices).norm(dim=1).max())
        renderers = [make_renderer(mesh, camera, backend) for backend in BACKENDS]
        for size in (a.roi, None):
            rois = windows(poses, camera, radius, size)
            label = f"{size}x{size}" if size else f"tracker ~{rois[0][2]}x{rois[0][3]}"
            for shaded in (True, False):
                ms = [ms_per_render(r, poses, rois, shaded, a.renders, a.rounds) for r in renderers]
                print(f"{len(mesh.faces):<6d} faces  {label:<20s}{'shaded' if shaded else 'depth':<8s}"
                      + "".join(f"{m:10.3f}" for m in ms) + f"{ms[0] / ms[1]:10.1f}x")
        for r in renderers:
            r.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
