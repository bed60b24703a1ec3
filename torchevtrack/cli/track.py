"""``torchevtrack track SEQDIR --out poses.txt``: track a sequence directory, write TUM poses.

A camera with lens distortion (``distortion`` in ``camera.json``) has its events undistorted while they
are read, chunk by chunk (:class:`torchevtrack.distortion.Undistorter`): the tracker renders its
templates with the pinhole ``K`` of the camera, so the events must live in that undistorted image too.
Events that land outside the sensor are dropped (the count is printed). ``--no-undistort`` tracks the
raw sensor pixels.

Exit status: 0 tracked; 2 bad input (one line on stderr, nothing written): unreadable or invalid events or camera,
``--out`` a directory, no events in the tracked span, a start pose that puts the object out of view; 3 the poses
were written but never moved from the start pose (a warning says why to look).

The loss detector, the re-localiser and its start search (:mod:`torchevtrack.recover`) are on unless ``--no-recover``
(a recording has moments the tracker cannot follow and an ``--init`` may be rough, and offline a search costs only
wall time; the library's config keeps them off, as a search blocks a streaming update for 0.3-1.5 s). With the loss
detector on the lost flags go to a side file beside ``--out`` (:mod:`torchevtrack.io.lost`: ``poses.txt`` ->
``poses.lost.txt``) and a warning says how long the object was lost.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import NamedTuple

import torch

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.io.lost import lost_path, write_lost
from torchevtrack.io.poses import read_tum, write_tum
from torchevtrack.tracker import EventPoseTracker
from torchevtrack.cli.options import (add_ablation_option, add_config_options, add_events_option, config_from_args,
                                      events_path, read_camera_events)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "track",
        help="track the object of a sequence directory",
        description="Track the object through SEQDIR (events.h5, camera.json, mesh.ply) and write the poses "
        "in TUM format (t tx ty tz qx qy qz qw, object in camera frame), one per update.",
    )
    add_recording_options(p)
    p.add_argument("--out", type=Path, required=True, help="output TUM pose file")
    add_config_options(p, "configs/default.yaml values")
    add_ablation_option(p)
    p.add_argument("--recover", action=argparse.BooleanOptionalAction, default=True,
                   help="detect tracking loss and find the object again with a wide search, and search once around "
                   "the start pose 48 ms in (on by default; blocks ~0.3-1.5 s per search); writes the lost flags to "
                   "OUT's side file (poses.txt -> poses.lost.txt)")
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


INIT_NORM_TOL = 0.01
"""``--init``'s quaternion may be this far from unit norm (two typed decimals round it by up to ~0.01); it is
renormalised."""


def parse_init(text: str) -> torch.Tensor:
    """``"tx ty tz qx qy qz qw"`` (TUM order, qw last) -> pose ``(7,)`` ``[t, qw, qx, qy, qz]``.

    The quaternion is renormalised: a rounded one (digits typed by hand, a detector's printout) has a norm within
    :data:`INIT_NORM_TOL` of 1. Raises ``ValueError`` unless there are 7 finite numbers whose quaternion's norm is
    that close to 1.

    Example:
        >>> round(parse_init("0 0 0.6 0 0 0.71 0.71")[3:].norm().item(), 12)  # typed with norm 1.004
        1.0
    """
    try:
        v = [float(s) for s in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"--init must be 7 numbers 'tx ty tz qx qy qz qw', got {text!r}") from None
    if len(v) != 7 or not all(math.isfinite(a) for a in v):
        raise ValueError(f"--init must be 7 finite numbers 'tx ty tz qx qy qz qw', got {text!r}")
    norm = math.sqrt(sum(a * a for a in v[3:]))
    if abs(norm - 1.0) > INIT_NORM_TOL:
        raise ValueError(f"--init quaternion 'qx qy qz qw' = {' '.join(f'{a:g}' for a in v[3:])} has norm {norm:.4g},"
                         " not 1")
    return torch.tensor(v[:3] + [a / norm for a in [v[6]] + v[3:6]], dtype=torch.float64)


SMALL_PX = 64
"""An object whose image spans fewer pixels at the start pose gets a warning. On the wide dev split (64 sequences, two
start draws each) such runs held 14-16 of 38 (turns 0-2 of 12) against 65 of 90 for larger objects: a box of ~45 px
gives the flow 3-7 vectors per update for the six unknowns of its motion (docs/method.md, Known limits)."""


def check_start_pose(camera: Camera, mesh, pose: torch.Tensor) -> str | None:
    """A warning if the object at ``pose`` (``(7,)``, ``[t, qw, qx, qy, qz]``) shows no edge to track (it fills
    the whole image or covers a handful of pixels) or is small (its image spans fewer than :data:`SMALL_PX` pixels);
    ``None`` if it is fine. Raises ``ValueError`` if no pixel of it is in view."""
    from torchevtrack.mesh import load_mesh
    from torchevtrack.raster import RasterRenderer

    with RasterRenderer(load_mesh(mesh), camera) as r:
        inside = r.render(pose[None]).depth[0] > 0
    seen = int(inside.sum())
    if seen == 0:
        t, q = pose[:3].tolist(), pose[3:].tolist()
        raise ValueError(f"the object is out of view at the start pose (t = {t[0]:g} {t[1]:g} {t[2]:g} m, "
                         f"qw qx qy qz = {' '.join(f'{a:g}' for a in q)}); --init takes 'tx ty tz qx qy qz qw'")
    if seen == inside.numel():
        return "the object fills the whole image at the start pose: it has no edge to track (too close?)"
    if seen < 20:
        return f"the object covers only {seen} pixels at the start pose: too few edges to track"
    rows, cols = inside.any(1).nonzero(), inside.any(0).nonzero()
    span = max(int(rows[-1] - rows[0]), int(cols[-1] - cols[0])) + 1
    if span < SMALL_PX:
        return (f"the object spans {span} px at the start pose: below {SMALL_PX} px its flow gives few vectors and "
                "fast turns out of the image plane are often lost (a closer object or a finer sensor helps)")
    return None


class Recording(NamedTuple):
    """What :func:`load_recording` reads: the camera, the (undistorted) events, the mesh (a path or an object name),
    the ground truth ``(t_us (M,), poses (M, 7))`` or ``None``, the start pose ``(7,)`` and its time (int64 us)."""

    camera: Camera
    events: EventStream
    mesh: Path | str
    truth: tuple[torch.Tensor, torch.Tensor] | None
    pose0: torch.Tensor
    t0_us: int


def add_recording_options(p: argparse.ArgumentParser) -> None:
    """Add the positional ``seqdir`` and ``--init``, ``--mesh``, ``--events`` (read by :func:`load_recording`)."""
    p.add_argument("seqdir", type=Path, help="sequence directory: camera.json, and by default events.h5, mesh.ply and "
                   "gt_poses.txt")
    p.add_argument("--init", help='initial pose "tx ty tz qx qy qz qw": metres, then a unit quaternion with qw '
                   "LAST (TUM order; the Python API's pose is [t, qw, qx, qy, qz]), at the first event (or at "
                   "--start); default: first pose of gt_poses.txt")
    p.add_argument("--start", type=float, metavar="SECONDS",
                   help="start tracking at this time (seconds in the events' time base, as in TUM files): --init is "
                   "the pose then; without --init, the first ground-truth pose at or after it (default: the first "
                   "event with --init, else the first ground-truth pose)")
    p.add_argument("--mesh", help="mesh file or object name (default: SEQDIR/mesh.ply)")
    add_events_option(p, "SEQDIR")


def load_recording(args: argparse.Namespace, undistort: bool = True) -> Recording:
    """The :class:`Recording` of ``args.seqdir`` with ``--events``, ``--mesh`` and ``--init`` (or the directory's
    events.h5, mesh.ply and first ground-truth pose). Raises ``FileNotFoundError`` / ``ValueError`` (one line) for
    a missing directory, file or start pose."""
    d = args.seqdir
    if not d.is_dir():
        raise FileNotFoundError(f"sequence directory not found: {d}")
    camera = Camera.load(d / "camera.json")
    events = read_camera_events(events_path(args, d), camera, undistort=undistort)
    mesh = args.mesh if args.mesh is not None else d / "mesh.ply"
    if args.mesh is None and not mesh.is_file():
        raise FileNotFoundError(f"{d} has no mesh.ply: give the object with --mesh")
    truth = read_tum(d / "gt_poses.txt") if (d / "gt_poses.txt").is_file() else None
    start = None if args.start is None else round(args.start * 1e6)
    if start is not None and not events.t_start <= start < events.t_end:
        raise ValueError(f"--start {args.start} s is outside the events ({events.t_start / 1e6:.6f} .. "
                         f"{events.t_end / 1e6:.6f} s)")
    if args.init is not None:
        pose0, t0 = parse_init(args.init), events.t_start if start is None else start
    elif truth is not None:
        k = 0 if start is None else int(torch.searchsorted(truth[0], start))
        if k == len(truth[0]):
            raise ValueError(f"gt_poses.txt ends at {int(truth[0][-1]) / 1e6:.6f} s, before --start {args.start} s")
        pose0, t0 = truth[1][k], int(truth[0][k])
    else:
        raise ValueError(f"{d} has no gt_poses.txt: give the initial pose with --init")
    return Recording(camera, events, mesh, truth, pose0, int(t0))


def rerun_logger(args: argparse.Namespace, camera: Camera, mesh, truth, tracker: EventPoseTracker):
    """The :class:`~torchevtrack.watch.RerunLogger` of ``--rerun`` / ``--rerun-spawn`` attached to ``tracker``,
    or None."""
    if args.rerun is None and not args.rerun_spawn:
        return None
    from torchevtrack.watch import RerunLogger

    return RerunLogger(camera, mesh, path=args.rerun, spawn=args.rerun_spawn, gt=truth).attach(tracker)


def run(args: argparse.Namespace) -> int:
    torch.set_num_threads(args.threads)
    if args.out.is_dir():
        raise ValueError(f"--out {args.out} is a directory: give a file name, e.g. {args.out / 'poses.txt'}")
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be positive seconds, got {args.duration}")
    camera, events, mesh, truth, pose0, t0 = load_recording(args, undistort=not args.no_undistort)
    cfg = config_from_args(args)
    t_end = t0 + round(args.duration * 1e6) if args.duration else events.t_end
    n_events = len(events.slice_time(t0, t_end + 1))
    if n_events == 0:
        raise ValueError(f"no events between t = {t0} and {t_end} us (the events span {events.t_start} .. "
                         f"{events.t_end} us): nothing to track")
    warning = check_start_pose(camera, mesh, pose0)
    if warning:
        print(f"torchevtrack track: warning: {warning}", file=sys.stderr)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tracker = EventPoseTracker(camera, mesh, cfg)
    logger = rerun_logger(args, camera, mesh, truth, tracker)
    start = time.perf_counter()
    try:
        times, poses, *lost = tracker.track(events, pose0, t_start_us=t0, t_end_us=t_end, progress=not args.quiet,
                                            return_lost=cfg.loss.enabled)
    finally:
        if logger is not None:
            logger.close()
    wall = time.perf_counter() - start
    tracker.close()
    write_tum(args.out, times[0], poses[0])
    n = times.shape[1]
    r = tracker.recover
    search_s = 0.0 if r is None else r.search_s  # a search blocks its update: the rate is the tracking's without it
    searching = f", and {search_s:.1f} s in {_count(r.searches, 'search', 'searches')}" if search_s > 0 else ""
    print(f"{args.out}: {n} poses from {n_events} events, {n / max(wall - search_s, 1e-9):.0f} updates/s "
          f"({wall - search_s:.1f} s{searching})")
    if lost:
        flags = lost[0][0]
        write_lost(lost_path(args.out), times[0], flags)
        searched = "" if r is None else \
            f"; {_count(r.searches, 'search', 'searches')}, {_count(r.restarts, 'restart', 'restarts')}"
        print(f"{lost_path(args.out)}: lost in {int(flags.sum())} of {n} updates{searched}")
        if flags.any():
            first = int(times[0][flags.nonzero()[0, 0]])
            print(f"torchevtrack track: warning: the object was lost in {int(flags.sum())} of {n} updates (first at "
                  f"t = {first / 1e6:.3f} s; {'still lost at the end' if flags[-1] else 'found again'})",
                  file=sys.stderr)
    if args.rerun is not None:
        print(f"rerun recording: {args.rerun} (open with: rerun {args.rerun})")
    if n and torch.allclose(poses[0], pose0.to(poses.dtype).expand_as(poses[0]), rtol=0.0, atol=1e-12):
        print(f"torchevtrack track: warning: the pose never moved from the start pose in {n} updates: check that "
              "the object is in view and the events are of it", file=sys.stderr)
        return 3
    return 0


def _count(n: int, one: str, many: str) -> str:
    """``n`` and its noun: ``_count(1, "search", "searches") == "1 search"``, ``"2 searches"`` for 2."""
    return f"{n} {one if n == 1 else many}"
