"""``torchevtrack track SEQDIR --out poses.txt``: track a sequence directory, write TUM poses.

A camera with lens distortion (``distortion`` in ``camera.json``) has its events undistorted while they
are read, chunk by chunk (:class:`torchevtrack.distortion.Undistorter`): the tracker renders its
templates with the pinhole ``K`` of the camera, so the events must live in that undistorted image too.
Events that land outside the sensor are dropped (the count is printed). ``--no-undistort`` tracks the
raw sensor pixels.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS
from torchevtrack.distortion import Undistorter
from torchevtrack.events import EventStream
from torchevtrack.io.events_h5 import iter_events_h5, read_events_h5
from torchevtrack.io.poses import read_tum, write_tum
from torchevtrack.tracker import EventPoseTracker
from torchevtrack.cli.options import add_config_options, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="track the object of a sequence directory",
        description="Track the object through SEQDIR (events.h5, camera.json, mesh.ply) and write the poses "
        "in TUM format (t tx ty tz qx qy qz qw, object in camera frame), one per update.",
    )
    p.add_argument("seqdir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output TUM pose file")
    add_config_options(p, "configs/default.yaml values")
    p.add_argument("--ablation", choices=sorted(ABLATIONS), default="full", help="the paper's ablations")
    p.add_argument("--init", help='initial pose "tx ty tz qx qy qz qw" (default: first pose of gt_poses.txt)')
    p.add_argument("--mesh", help="mesh file or object name (default: SEQDIR/mesh.ply)")
    p.add_argument("--duration", type=float, help="track only the first SECONDS")
    p.add_argument("--no-undistort", action="store_true",
                   help="do not undistort the events of a camera with distortion coefficients")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest for one sequence)")
    p.add_argument("--rerun", type=Path, metavar="FILE.rrd",
                   help="log every update to this rerun recording (EROS, contours, mesh, trajectory, errors, timings; "
                   "needs the rerun extra)")
    p.add_argument("--rerun-spawn", action="store_true", help="stream the same to a rerun viewer started now")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def parse_init(text: str) -> torch.Tensor:
    """``"tx ty tz qx qy qz qw"`` (TUM order) -> pose ``(7,)`` ``[t, qw, qx, qy, qz]``."""
    try:
        v = [float(s) for s in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"--init must be 7 numbers 'tx ty tz qx qy qz qw', got {text!r}") from None
    if len(v) != 7:
        raise ValueError(f"--init must be 7 numbers 'tx ty tz qx qy qz qw', got {len(v)}")
    return torch.tensor(v[:3] + [v[6]] + v[3:6], dtype=torch.float64)


def undistorted_events(path: Path, camera: Camera, chunk: int = 1_000_000) -> EventStream:
    """Read an events.h5 file ``chunk`` events at a time, moving each chunk into the pinhole image of
    ``camera`` (its distortion coefficients, :class:`~torchevtrack.distortion.Undistorter`); prints the
    number of dropped events."""
    undistort = Undistorter(camera)
    events = EventStream.concat([undistort(c) for c in iter_events_h5(path, chunk, width=camera.width,
                                                                      height=camera.height)])
    print(f"undistorted {len(events) + int(undistort.dropped)} events, dropped {int(undistort.dropped)} "
          "(outside the pinhole image)")
    return events


def rerun_logger(args: argparse.Namespace, camera: Camera, mesh, truth, tracker: EventPoseTracker):
    """The :class:`~torchevtrack.watch.RerunLogger` of ``--rerun`` / ``--rerun-spawn`` attached to ``tracker``,
    or None."""
    if args.rerun is None and not args.rerun_spawn:
        return None
    from torchevtrack.watch import RerunLogger

    return RerunLogger(camera, mesh, path=args.rerun, spawn=args.rerun_spawn, gt=truth).attach(tracker)


def run(args: argparse.Namespace) -> int:
    torch.set_num_threads(args.threads)
    d = args.seqdir
    if not d.is_dir():
        raise FileNotFoundError(f"sequence directory not found: {d}")
    camera = Camera.load(d / "camera.json")
    if camera.distortion is not None and not args.no_undistort:
        events = undistorted_events(d / "events.h5", camera)
    else:
        events = read_events_h5(d / "events.h5")
        events.validate(camera.width, camera.height)
    mesh = args.mesh if args.mesh is not None else d / "mesh.ply"
    if args.mesh is None and not mesh.is_file():
        raise FileNotFoundError(f"{d} has no mesh.ply: give the object with --mesh")
    truth = read_tum(d / "gt_poses.txt") if (d / "gt_poses.txt").is_file() else None
    if args.init is not None:
        pose0, t0 = parse_init(args.init), events.t_start
    elif truth is not None:
        pose0, t0 = truth[1][0], int(truth[0][0])
    else:
        raise ValueError(f"{d} has no gt_poses.txt: give the initial pose with --init")
    cfg = config_from_args(args)
    cfg = cfg.replace(**ABLATIONS[args.ablation])
    tracker = EventPoseTracker(camera, mesh, cfg)
    logger = rerun_logger(args, camera, mesh, truth, tracker)
    t_end = t0 + round(args.duration * 1e6) if args.duration else None
    start = time.perf_counter()
    try:
        times, poses = tracker.track(events, pose0, t_start_us=t0, t_end_us=t_end, progress=not args.quiet)
    finally:
        if logger is not None:
            logger.close()
    wall = time.perf_counter() - start
    tracker.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_tum(args.out, times[0], poses[0])
    n = times.shape[1]
    print(f"{args.out}: {n} poses, {n / wall:.0f} updates/s ({wall:.1f} s)")
    if args.rerun is not None:
        print(f"rerun recording: {args.rerun} (open with: rerun {args.rerun})")
    return 0
