"""``torchevtrack synth`` (one synthetic sequence) and ``torchevtrack synth-benchmark`` (the standard 8 or a
split of the wide suite, :mod:`torchevtrack.synth.suite`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from torchevtrack.camera import Camera
from torchevtrack.cli.options import add_executor_options, executor_from_args
from torchevtrack.synth.suite import CAMERA_PRESETS, MOTIONS
from torchevtrack.synth.trajectory import SLIDE_S, back_on_path_s


def _camera(args: argparse.Namespace) -> Camera:
    d = CAMERA_PRESETS[args.camera]
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
        refractory_us=args.refractory_us, noise_rate_hz=args.noise_rate, hot_pixels=args.hot_pixels,
        hot_pixel_rate_hz=args.hot_pixel_rate, occluder=args.occluder, texture=args.texture,
        depth_range=args.depth, background=args.background, render_faces=args.render_faces,
        render_backend=args.render_backend, leave_view=args.leave_view, progress=not args.quiet,
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


def _depth(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX metres, got {text!r}") from None
    if not 0 < lo < hi:
        raise argparse.ArgumentTypeError(f"need 0 < MIN < MAX, got {text!r}")
    return lo, hi


def _leave_view(text: str) -> tuple[float, float]:
    try:
        start, away = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START,AWAY seconds, got {text!r}") from None
    if not (start >= 0 and away >= 0):
        raise argparse.ArgumentTypeError(f"need START >= 0 and AWAY >= 0 seconds, got {text!r}")
    return start, away


def _add_world(g: argparse._ArgumentGroup) -> None:
    """The flags of one sequence's world beyond the standard benchmark's (``synth`` only)."""
    from torchevtrack.render import BACKENDS
    from torchevtrack.synth.generate import OCCLUDERS, TEXTURES

    g.add_argument("--hot-pixels", type=int, default=0, help="number of hot pixels (seeded addresses)")
    g.add_argument("--hot-pixel-rate", type=float, default=100.0, help="events per second of each hot pixel")
    g.add_argument("--occluder", choices=OCCLUDERS, default="none",
                   help="hand: a hand holds the object at one end (its own events; hides part of the silhouette)")
    g.add_argument("--texture", choices=TEXTURES, default="none",
                   help="random: a seeded printed texture (its model: mesh_textured.glb)")
    g.add_argument("--depth", type=_depth, default=(0.3, 0.7), metavar="MIN,MAX",
                   help="object distance range, metres (default 0.3,0.7; raised for objects too large to fit)")
    g.add_argument("--leave-view", type=_leave_view, metavar="START,AWAY",
                   help="the object slides out of the view at START s (over 0.35 s), stays out AWAY s and slides back")
    g.add_argument("--render-backend", choices=BACKENDS, default="pyrender",
                   help="renderer of the frames (raster: compiled CPU z-buffer, several times faster)")


def run_synth(args: argparse.Namespace) -> int:
    if args.duration <= 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    if args.leave_view is not None and back_on_path_s(*args.leave_view) > args.duration:
        raise ValueError(f"--leave-view {args.leave_view[0]:g},{args.leave_view[1]:g}: the object would not be back "
                         f"in view by the end of the {args.duration:g} s sequence (it slides {SLIDE_S:g} s each way)")
    _generate(args.object, args.motion, args.duration, args.seed, _camera(args), Path(args.out), args)
    return 0


def run_benchmark(args: argparse.Namespace) -> int:
    from torchevtrack.synth.suite import (
        SPLIT_SEED_BASE,
        generate_suite,
        object_sizes,
        standard_suite,
        wide_suite,
        write_suite_json,
    )

    if args.duration is not None and args.duration <= 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    out = Path(args.out)
    if args.suite == "standard":
        if args.split is not None or args.seed_base is not None or args.objects is not None:
            raise ValueError("--split, --seed-base and --objects choose a split of --suite wide")
        entries = standard_suite(4.0 if args.duration is None else args.duration,
                                 contrast_threshold=args.contrast_threshold, sigma_c=args.sigma_c,
                                 refractory_us=args.refractory_us, noise_rate=args.noise_rate,
                                 background=args.background, render_faces=args.render_faces)
        split, base = None, None
    else:
        if args.split is None:
            raise ValueError("--suite wide needs --split dev or --split test")
        if args.noise_rate != 0.0 or args.refractory_us != 0:
            raise ValueError("--noise-rate and --refractory-us are drawn per sequence by the wide suite")
        split = args.split
        base = SPLIT_SEED_BASE[split] if args.seed_base is None else args.seed_base
        entries = wide_suite(split, base, None if args.objects is None else object_sizes(args.objects))
        for e in entries:
            e.update(contrast_threshold=args.contrast_threshold, sigma_c=args.sigma_c, background=args.background,
                     render_faces=args.render_faces)
            if args.duration is not None:
                e["duration"] = float(args.duration)
    names = [e["name"] for e in entries]
    only = set(args.only or [])
    if only - set(names):
        raise ValueError(f"--only: unknown sequence(s) {sorted(only - set(names))}; choose from {names}")
    path = write_suite_json(out, args.suite, split, base, entries)
    if args.dry_run:
        print(f"{path}: {len(entries)} sequences (dry run, nothing generated)")
        return 0
    todo = [e for e in entries if not only or e["name"] in only]
    print(f"generating {len(todo)} sequence(s) into {out}; a 4 s sequence takes about 10 s (slow, small camera) to "
          "several minutes (fast, hd) of one core")
    start = time.perf_counter()
    if args.executor == "process" and args.address is None:  # the suite's own pool, sized to the work
        results = generate_suite(todo, out, jobs=args.jobs, progress=not args.quiet)
    else:
        with executor_from_args(args) as executor:
            results = generate_suite(todo, out, executor=executor, progress=not args.quiet)
    took = time.perf_counter() - start
    print(f"{len(results)} sequences in {took:.1f} s wall ({sum(r['seconds'] for r in results):.1f} s of workers)")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="simulate one synthetic event sequence",
        description="Render an object along a seeded random trajectory and simulate its events (ESIM). "
        "Writes events.h5, camera.json, gt_poses.txt, mesh.ply and meta.json into --out.",
    )
    p.add_argument("--object", required=True, help="box, can, bottle, a YCB name (006_mustard_bottle) or a mesh file")
    p.add_argument("--motion", choices=MOTIONS, default="regular",
                   help="motion group: regular, fast, turn (hand-held turns, 240-440 deg/s median) or mixed "
                   "(fast translation and turns)")
    p.add_argument("--duration", type=float, default=4.0, help="seconds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output sequence directory")
    g = p.add_argument_group("camera (default: 640x480, fx = fy = 502.3, principal point at the centre)")
    g.add_argument("--camera", choices=CAMERA_PRESETS, default="vga",
                   help="sensor preset: davis346 (346x260, f 255), vga (640x480, f 502.3), hd (1280x720, f 1000); "
                   "the flags below override its values")
    for name in ("width", "height"):
        g.add_argument(f"--{name}", type=int)
    for name in ("fx", "fy", "cx", "cy"):
        g.add_argument(f"--{name}", type=float)
    _add_common(p)
    _add_world(p.add_argument_group("world"))
    p.set_defaults(func=run_synth)

    b = subparsers.add_parser(
        "synth-benchmark",
        help="simulate a benchmark suite: the standard 8 sequences or a split of the wide suite",
        description="--suite standard (default): cracker / mustard / potted / tomato (YCB meshes) x regular / fast, "
        "fixed seeds, default camera. --suite wide --split dev|test: 32 sequences of 12 YCB objects, four motion "
        "groups, three cameras, sensor noise, hot pixels, refractory periods, a hand and printed textures. One "
        "directory per sequence under --out, and --out/suite.json listing them (with each one's factors).",
    )
    b.add_argument("--out", required=True, help="output directory")
    b.add_argument("--suite", choices=("standard", "wide"), default="standard")
    b.add_argument("--split", choices=("dev", "test"), help="the wide suite's split (dev: tune on it; test: report)")
    b.add_argument("--seed-base", type=int, help="the wide suite's first seed (default: the split's)")
    b.add_argument("--duration", type=float, help="seconds per sequence (default 4)")
    b.add_argument("--objects", nargs="+", metavar="OBJECT",
                   help="the wide suite drawn over these objects (names as --object of synth, or mesh files) instead "
                   "of its 12 YCB objects; every other factor of each sequence stays the split's")
    b.add_argument("--only", nargs="+", metavar="NAME", help="generate only these sequences (e.g. mustard_fast)")
    b.add_argument("--dry-run", action="store_true", help="write only --out/suite.json")
    add_executor_options(b, default="process")
    _add_common(b)
    b.set_defaults(func=run_benchmark)
