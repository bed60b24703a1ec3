"""Milliseconds per render of the raster backend on a benchmark sequence, the tracker's way, optionally against
another version of ``torchevtrack/raster.py`` (same process, interleaved rounds, outputs compared).

Each render is one ground-truth pose of the sequence (every ``--step``-th), shaded, in the tracker's window
(:func:`torchevtrack.stages.template.render_window` with the mesh's bounding radius and a 24 px margin, clipped
to the frame). Timing: CPU time (``time.process_time``) of the compiled kernel alone and of
:meth:`RasterRenderer.render`, 1 torch thread, best of ``--rounds`` rounds over all poses, after a warm-up.

    .venv/bin/python tools/bench_raster.py [--sequence data/bench/mustard_fast] [--baseline old_raster.py]
    .venv/bin/python tools/bench_raster.py --texture 1   # the mesh with a printed texture, against it untextured

``--baseline`` takes a copy of the module, e.g. ``git show HEAD~1:torchevtrack/raster.py > /tmp/raster_old.py``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time

import numpy as np
import torch

from torchevtrack import raster
from torchevtrack.render import AMBIENT, LIGHT_DIRECTION
from torchevtrack.stages.template import render_window
from torchevtrack.synth.sequence import Sequence


def load_module(path: str):
    spec = importlib.util.spec_from_file_location("raster_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # for numba's cache
    spec.loader.exec_module(module)
    return module


def windows(poses: torch.Tensor, camera, radius: float) -> list[tuple[int, int, int, int]]:
    """The tracker's clipped render windows (``EventPoseTracker._windows``)."""
    win = render_window(poses, camera, radius, 24)
    w, h = win[:, 2].clamp(max=camera.width), win[:, 3].clamp(max=camera.height)
    u = win[:, 0].clamp(min=0).minimum(camera.width - w)
    v = win[:, 1].clamp(min=0).minimum(camera.height - h)
    return [tuple(r) for r in torch.stack((u, v, w, h), -1).tolist()]


def kernel_pass(module, mesh, poses, cams, outs, texture=None) -> float:
    """CPU seconds of one kernel call per pose (into preallocated outputs)."""
    extra = () if texture is None else (tuple(texture),)
    t0 = time.process_time()
    kernel = getattr(module, "render_kernel", None) or module._render_kernel  # a baseline copy may name it so
    for p, cam, (depth, gray) in zip(poses, cams, outs):
        kernel(*mesh, p, cam.fx, cam.fy, cam.cx, cam.cy, 0.01, 20.0, LIGHT_DIRECTION, AMBIENT, 0.0, depth, gray, *extra)
    return time.process_time() - t0


def render_pass(renderer, poses, rois) -> float:
    t0 = time.process_time()
    for p, roi in zip(poses, rois):
        renderer.render(p, roi=roi, shaded=True)
    return time.process_time() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="data/bench/mustard_fast")
    ap.add_argument("--step", type=int, default=10, help="every step-th ground-truth pose")
    ap.add_argument("--rounds", type=int, default=7)
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--baseline", help="path of another raster.py to compare with")
    group.add_argument("--texture", type=int, metavar="SEED",
                       help="also time the mesh with torchevtrack.synth.texture.printed_texture(mesh, SEED)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    seq = Sequence.load(a.sequence)
    poses = seq.gt_poses[::a.step]
    radius = float(np.linalg.norm(seq.mesh.vertices, axis=1).max())
    rois = windows(poses, seq.camera, radius)
    cams = [seq.camera.crop(*r) for r in rois]
    np_poses = [p[None].numpy().copy() for p in poses]
    runs = {"current": (raster, seq.mesh)}
    if a.baseline:
        runs["baseline"] = (load_module(a.baseline), seq.mesh)
    if a.texture is not None:
        from torchevtrack.synth.texture import printed_texture

        runs["textured"] = (raster, printed_texture(seq.mesh, a.texture))
    results = {}
    for name, (module, model) in runs.items():
        renderer = module.RasterRenderer(model, seq.camera)
        mesh, texture = renderer.raster_mesh, getattr(renderer, "raster_texture", None)
        outs = [(np.empty((1, c.height, c.width), np.float32), np.empty((1, c.height, c.width), np.float32))
                for c in cams]
        kernel_pass(module, mesh, np_poses, cams, outs, texture)  # warm-up (compile or cache load)
        results[name] = dict(module=module, mesh=mesh, texture=texture, outs=outs, kernel=[], render=[],
                             renderer=renderer)
    for _ in range(a.rounds):
        for r in results.values():
            r["kernel"].append(kernel_pass(r["module"], r["mesh"], np_poses, cams, r["outs"], r["texture"]))
            r["render"].append(render_pass(r["renderer"], poses, rois))
    n = len(poses)
    area = np.mean([c.width * c.height for c in cams])
    print(f"{a.sequence}: {n} poses, {len(seq.mesh.faces)} faces, mean window {area:.0f} px; ms per render "
          f"(process time, best / median of {a.rounds} rounds)")
    for name, r in results.items():
        k, rr = np.array(r["kernel"]) / n * 1e3, np.array(r["render"]) / n * 1e3
        print(f"  {name:<9s} kernel {k.min():.3f} / {np.median(k):.3f}   render() {rr.min():.3f} / {np.median(rr):.3f}")
    if a.baseline:
        cur, base = results["current"]["outs"], results["baseline"]["outs"]
        dd = max(float(np.abs(c[0] - b[0]).max()) for c, b in zip(cur, base))
        dg = max(float(np.abs(c[1] - b[1]).max()) for c, b in zip(cur, base))
        sil = sum(int(((c[0] > 0) != (b[0] > 0)).sum()) for c, b in zip(cur, base))
        same = all(np.array_equal(c[0], b[0]) and np.array_equal(c[1], b[1]) for c, b in zip(cur, base))
        print(f"  vs baseline: identical {same}; max |depth diff| {dd:.3g} m, max |gray diff| {dg:.3g}, "
              f"silhouette pixels differing {sil}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
