"""``torchevtrack synth`` (one synthetic sequence) and ``torchevtrack synth-benchmark`` (the standard 8)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from torchevtrack.camera import Camera

# The paper's synthetic benchmark: 4 YCB objects x 2 motion groups, named like the paper's tables.
BENCHMARK_OBJECTS = {
    "cracker": "003_cracker_box",
    "mustard": "006_mustard_bottle",
    "potted": "010_potted_meat_can",
    "tomato": "005_tomato_soup_can",
}
BENCHMARK_MOTIONS = ("regular", "fast")


def benchmark_seed(short: str, motion: str) -> int:
    """Fixed seed of a benchmark sequence (stable across releases)."""
    return 1000 + 10 * list(BENCHMARK_OBJECTS).index(short) + BENCHMARK_MOTIONS.index(motion)


def _camera(args: argparse.Namespace) -> Camera:
    d = Camera.default()
    return Camera(
        args.width if args.width is not None else d.width,
        args.height if args.height is not None else d.height,
        args.fx if args.fx is not None else d.fx,
        args.fy if args.fy is not None else d.fy,
        args.cx if args.cx is not None else args.width / 2 if args.width is not None else d.cx,
        args.cy if args.cy is not None else args.height / 2 if args.height is not None else d.cy,
    )


def _generate(object_name: str, motion: str, duration: float, seed: int, camera: Camera, out: Path,
              args: argparse.Namespace) -> None:
    from torchevtrack.synth.generate import generate_sequence

    start = time.perf_counter()
    seq = generate_sequence(
        object_name, motion, duration, seed, camera, C=args.contrast_threshold, sigma_C=args.sigma_c,
        refractory_us=args.refractory_us, noise_rate_hz=args.noise_rate, background=args.background,
        render_faces=args.render_faces, progress=not args.quiet,
    )
    seq.save(out)
    took = time.perf_counter() - start
    s = seq.meta["speeds"]["image_speed_px_s"]
    print(
        f"{out}: {len(seq.events)} events ({seq.meta['events_per_s'] / 1e6:.2f} Mev/s), "
        f"{seq.meta['generator']['n_frames']} frames, centroid speed median {s['median']:.0f} px/s, "
        f"generated in {took:.1f} s ({took / duration:.1f} s per sequence second)"
    )


def _add_common(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("simulator")
    g.add_argument("--contrast-threshold", type=float, default=0.2, help="mean contrast threshold C (log units)")
    g.add_argument("--sigma-c", type=float, default=0.03, help="per-pixel threshold spread")
    g.add_argument("--refractory-us", type=int, default=0, help="refractory period, microseconds")
    g.add_argument("--noise-rate", type=float, default=0.0, help="uniform noise events per pixel per second")
    g.add_argument("--background", type=float, default=0.2, help="grey level of the static background")
    g.add_argument("--render-faces", type=int, help="render a mesh decimated to about this many faces")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run_synth(args: argparse.Namespace) -> int:
    if args.duration <= 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    _generate(args.object, args.motion, args.duration, args.seed, _camera(args), Path(args.out), args)
    return 0


def run_benchmark(args: argparse.Namespace) -> int:
    if args.duration <= 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    out = Path(args.out)
    only = set(args.only or [])
    names = {f"{short}_{motion}" for short in BENCHMARK_OBJECTS for motion in BENCHMARK_MOTIONS}
    if only - names:
        raise ValueError(f"--only: unknown sequence(s) {sorted(only - names)}; choose from {sorted(names)}")
    for short, name in BENCHMARK_OBJECTS.items():
        for motion in BENCHMARK_MOTIONS:
            seq_name = f"{short}_{motion}"
            if only and seq_name not in only:
                continue
            _generate(name, motion, args.duration, benchmark_seed(short, motion), Camera.default(),
                      out / seq_name, args)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="simulate one synthetic event sequence",
        description="Render an object along a seeded random trajectory and simulate its events (ESIM). "
        "Writes events.h5, camera.json, gt_poses.txt, mesh.ply and meta.json into --out.",
    )
    p.add_argument("--object", required=True, help="box, can, bottle, a YCB name (006_mustard_bottle) or a mesh file")
    p.add_argument("--motion", choices=BENCHMARK_MOTIONS, default="regular", help="motion group")
    p.add_argument("--duration", type=float, default=4.0, help="seconds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output sequence directory")
    g = p.add_argument_group("camera (default: 640x480, fx = fy = 502.3, principal point at the centre)")
    for name in ("width", "height"):
        g.add_argument(f"--{name}", type=int)
    for name in ("fx", "fy", "cx", "cy"):
        g.add_argument(f"--{name}", type=float)
    _add_common(p)
    p.set_defaults(func=run_synth)

    b = subparsers.add_parser(
        "synth-benchmark",
        help="simulate the standard 8 benchmark sequences",
        description="cracker / mustard / potted / tomato (YCB meshes) x regular / fast, fixed seeds, default "
        "camera; one directory per sequence (e.g. mustard_regular, cracker_fast) under --out.",
    )
    b.add_argument("--out", required=True, help="output directory")
    b.add_argument("--duration", type=float, default=4.0, help="seconds per sequence")
    b.add_argument("--only", nargs="+", metavar="NAME", help="generate only these sequences (e.g. mustard_fast)")
    _add_common(b)
    b.set_defaults(func=run_benchmark)
