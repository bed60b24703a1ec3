"""``torchevtrack live SOURCE --camera camera.json --mesh MESH --init "..."``: track a live event source.

SOURCE is ``tcp://HOST:PORT`` (an AEDAT4 event stream served by DV software or dv-processing's NetworkWriter),
``camera`` / ``camera:NAME`` (an iniVation camera through dv-processing) or a recording file (``--realtime`` plays
it at the pace of its time stamps). The tracker starts at ``--init`` on the first event's time. A status line per
second gives the poses, the update rate, the lag behind real time and the late / dropped events. The run ends with
the stream, or cleanly on Ctrl-C; the poses (TUM) are written to ``--out`` atomically (a temporary file renamed),
also every few seconds while running.

Example:
    torchevtrack live tcp://127.0.0.1:7777 --camera camera.json --mesh can --init "0 0 0.4 0 0 0 1" --out live.txt
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

import torch

from torchevtrack.cli.options import add_config_options, config_from_args

_STATUS_S = 1.0
_SAVE_S = 5.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "live",
        help="track a live event source (network stream, camera, paced recording)",
        description="Track the object in a live event source with the streaming tracker: SOURCE is tcp://HOST:PORT "
        "(an AEDAT4 event stream, as DV software and dv-processing's NetworkWriter serve), camera or camera:NAME "
        "(dv-processing), or a recording file. Prints the live rate, the lag and the late / dropped events once "
        "a second; stops at the end of the stream or on Ctrl-C with every pose written.",
    )
    p.add_argument("source", help="tcp://HOST:PORT, camera[:NAME] or an event file")
    p.add_argument("--camera", type=Path, required=True, help="camera.json (intrinsics; its size must match the "
                   "source's)")
    p.add_argument("--mesh", required=True, help="mesh file or object name")
    p.add_argument("--init", required=True, help='pose at the first event, "tx ty tz qx qy qz qw"')
    p.add_argument("--out", type=Path, help="write the poses here (TUM), atomically, also while running")
    p.add_argument("--realtime", action="store_true", help="play a recording file at the pace of its time stamps")
    add_config_options(p)
    p.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="log every update to this rerun recording")
    p.add_argument("--rerun-spawn", action="store_true", help="stream the updates to a rerun viewer started now")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no status lines")
    p.set_defaults(func=run)


class PoseFile:
    """The TUM file of a growing trajectory, rewritten whole and atomically at each :meth:`save` (a reader sees the
    old file or the new one, never a part), each pose formatted once: saving every few seconds of an hour's run
    costs the file's bytes, not the formatting of every pose again (1.3 s for 300,000 poses here)."""

    def __init__(self, path: Path) -> None:
        from torchevtrack.io.poses import TUM_HEADER

        self.path, self.lines = path, [TUM_HEADER]

    @property
    def poses(self) -> int:
        """Poses written so far."""
        return len(self.lines) - 1

    def save(self, t_us: torch.Tensor, poses: torch.Tensor) -> None:
        """Add the poses ``(N, 7)`` at ``t_us`` ``(N,)`` (those after the ones already written) and rewrite the file."""
        from torchevtrack.io.atomic import write_text
        from torchevtrack.io.poses import tum_lines

        self.lines.extend(tum_lines(t_us, poses))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_text(self.path, "\n".join(self.lines) + "\n")


def warm_up(tracker, pose0: torch.Tensor) -> None:
    """Every kernel loaded (:func:`torchevtrack.kernels.load`) and one update on an empty window, so that the
    stream's first updates do not wait for compiled code to load. The stream's start resets the tracker completely."""
    from torchevtrack.kernels import load

    load()
    empty = torch.zeros(0, dtype=torch.int64)
    tracker.reset(pose0)
    tracker(empty, empty, empty, empty)


def run(args: argparse.Namespace) -> int:
    from torchevtrack.camera import Camera
    from torchevtrack.cli.track import parse_init
    from torchevtrack.distortion import Undistorter
    from torchevtrack.live import AHEAD_EVENTS, LiveRunner, open_source, parse_source
    from torchevtrack.online import OnlineTracker
    from torchevtrack.tracker import EventPoseTracker

    parse_source(args.source, realtime=args.realtime)  # a bad source fails now, not after the warm-up
    torch.set_num_threads(args.threads)
    camera = Camera.load(args.camera)
    pose0 = parse_init(args.init)
    cfg = config_from_args(args)
    tracker = EventPoseTracker(camera, args.mesh, cfg)
    warm_up(tracker, pose0)
    source = open_source(args.source, realtime=args.realtime)
    if source.width is not None and (source.width, source.height) != (camera.width, camera.height):
        tracker.close()
        raise ValueError(f"the source is {source.width}x{source.height} pixels, the camera {args.camera} "
                         f"{camera.width}x{camera.height}")
    logger = None
    if args.rerun is not None or args.rerun_spawn:
        from torchevtrack.watch import RerunLogger

        logger = RerunLogger(camera, args.mesh, path=args.rerun, spawn=args.rerun_spawn).attach(tracker)
    runner = LiveRunner(OnlineTracker(tracker), pose0,
                        undistort=Undistorter(camera) if camera.distortion is not None else None)

    stop = []

    def on_sigint(signum, frame):
        if stop:  # a second Ctrl-C: stop now
            raise KeyboardInterrupt
        stop.append(True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    out = None if args.out is None else PoseFile(args.out)
    last_status = last_save = time.perf_counter()
    ahead = f"; its first {AHEAD_EVENTS // 1_000_000} M events are decoded before its clock starts (about 1 s per " \
        "10 M)" if args.realtime else ""
    print(f"live: tracking {args.source} (Ctrl-C to stop){ahead}", flush=True)
    try:
        for chunk in source:
            runner.feed(chunk)
            now = time.perf_counter()
            if now - last_status >= _STATUS_S:
                last_status = now
                if not args.quiet:
                    print(runner.report().line(), flush=True)
            if out is not None and now - last_save >= _SAVE_S and runner.status.poses > out.poses:
                last_save = now
                out.save(*runner.trajectory(since=out.poses))
            if stop:
                break
    finally:
        signal.signal(signal.SIGINT, previous)
        if logger is not None:
            logger.close()
        tracker.close()
        if out is not None and runner.status.poses > out.poses:
            out.save(*runner.trajectory(since=out.poses))
    status = runner.report()
    print(status.line(), flush=True)
    how = "stopped (Ctrl-C)" if stop else "end of stream"
    where = f", written to {args.out}" if args.out is not None and status.poses else ""
    print(f"live: {how}: {status.poses} poses{where}", file=sys.stdout, flush=True)
    return 0
