"""``torchevtrack viz``: mesh contours at the tracked (and ground-truth) poses over the EROS surface.

Works on a sequence directory (events.h5 or ``--events FILE`` in any readable format, camera.json, optionally
gt_poses.txt and mesh.ply) and any pose file; a directory without gt_poses.txt (a real recording) shows the tracked
contour only. The events of a camera with distortion coefficients are undistorted as ``track`` reads them.

Examples:
    torchevtrack viz data/seq0 --poses out/seq0_poses.txt --out seq0.gif --every-ms 20 --fps 25
    torchevtrack viz data/seq0 --poses out/seq0_poses.txt --out frame.png --time 1.5
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchevtrack.camera import Camera
from torchevtrack.cli.options import add_events_option, events_path, read_camera_events
from torchevtrack.io.poses import FORMATS, detect_format, read_poses, read_tum

US_PER_S = 1_000_000


def _frame_times(pred_t: torch.Tensor, args: argparse.Namespace, still: bool) -> torch.Tensor:
    """Frame times (us) inside the tracked range: one at --time for a still, else every --every-ms
    from --start (default: first tracked pose) for --duration (default: to the last tracked pose)."""
    lo, hi = int(pred_t[0]), int(pred_t[-1])
    span = f"[{lo / US_PER_S:.6f}, {hi / US_PER_S:.6f}] s"
    if still:
        t = (lo + hi) // 2 if args.time is None else round(args.time * US_PER_S)
        if not lo <= t <= hi:
            raise ValueError(f"--time {t / US_PER_S:g} s is outside the tracked poses {span}")
        return torch.tensor([t], dtype=torch.int64)
    if not args.every_ms > 0:
        raise ValueError(f"--every-ms must be positive, got {args.every_ms}")
    start = lo if args.start is None else round(args.start * US_PER_S)
    if not lo <= start <= hi:
        raise ValueError(f"--start {start / US_PER_S:g} s is outside the tracked poses {span}")
    end = hi
    if args.duration is not None:
        if not args.duration > 0:
            raise ValueError(f"--duration must be positive, got {args.duration}")
        end = min(hi, start + round(args.duration * US_PER_S))
    return torch.arange(start, end + 1, max(1, round(args.every_ms * 1000)), dtype=torch.int64)


def run(args: argparse.Namespace) -> int:
    import imageio.v3 as iio
    from tqdm import tqdm

    from torchevtrack.viz import VIDEO_EXTENSIONS, iter_overlay_frames, save_video

    seq = Path(args.sequence)
    if not seq.is_dir():
        raise FileNotFoundError(f"sequence directory not found: {seq}")
    out = Path(args.out)
    ext = out.suffix.lower()
    if ext not in VIDEO_EXTENSIONS + (".png",):
        raise ValueError(f"--out must end with .png (one frame) or one of {VIDEO_EXTENSIONS}, got {out}")
    if not (seq / "camera.json").is_file():
        raise FileNotFoundError(f"sequence {seq} lacks camera.json")
    ev_path = events_path(args, seq)
    mesh = args.mesh if args.mesh is not None else seq / "mesh.ply"
    if args.mesh is None and not Path(mesh).is_file():
        raise FileNotFoundError(f"sequence {seq} has no mesh.ply: pass --mesh (a file or a built-in object name)")

    camera = Camera.load(seq / "camera.json")
    pred_path = Path(args.poses)
    fmt = args.poses_format or detect_format(pred_path)
    bop = {k: v for k, v in (("fps", args.poses_fps), ("obj_id", args.obj_id)) if v is not None}
    pred = read_poses(pred_path, format=fmt, **(bop if fmt == "bop" else {}))
    gt_path = seq / "gt_poses.txt"
    gt = read_tum(gt_path) if gt_path.is_file() and not args.no_gt else None
    times = _frame_times(pred[0], args, still=ext == ".png")
    events = read_camera_events(ev_path, camera)  # undistorted as `track` reads them: the poses live in that image

    frames = iter_overlay_frames(events, camera, mesh, pred, times, gt, kernel_size=args.kernel_size,
                                 decay=args.decay, depth_jump=args.depth_jump, legend=not args.no_legend)
    frames = tqdm(frames, total=times.numel(), desc="viz", unit="frame", disable=args.quiet)
    out.parent.mkdir(parents=True, exist_ok=True)
    if ext == ".png":
        (frame,) = list(frames)
        iio.imwrite(out, frame)
        written = out
    else:
        written = save_video(frames, out, fps=args.fps)
    if not args.quiet:
        what = "1 frame" if ext == ".png" else f"{times.numel()} frames"
        print(f"{written}: {what}, {times[0] / US_PER_S:.3f}..{times[-1] / US_PER_S:.3f} s"
              + ("" if gt is not None else " (no ground truth)"))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "viz",
        help="overlay video / image of mesh contours over the event surface",
        description=(
            "Draw the mesh contour at the tracked poses (green) and, when the directory has gt_poses.txt, "
            "at the ground-truth poses (magenta) over the EROS surface of the events. Poses are "
            "interpolated at the frame times, never extrapolated: frames cover the tracked time range. "
            "Writes a GIF or MP4 (by extension; MP4 needs imageio-ffmpeg, else a GIF is written), or one "
            "PNG frame at --time."
        ),
    )
    p.add_argument("sequence", help="sequence directory (events.h5, camera.json, [gt_poses.txt], [mesh.ply])")
    p.add_argument("--poses", required=True, help="tracked pose file (TUM .txt, CSV .csv, BOP .json)")
    p.add_argument("--out", required=True, help="output .gif / .mp4, or .png for a single frame")
    p.add_argument("--mesh", help="mesh file or built-in object name (default: SEQUENCE/mesh.ply)")
    add_events_option(p, "SEQUENCE")
    p.add_argument("--fps", type=float, default=30.0, help="video frame rate (default 30)")
    p.add_argument("--every-ms", type=float, default=20.0, help="sequence time between frames (default 20 ms)")
    p.add_argument("--start", type=float, help="first frame time, seconds (default: first tracked pose)")
    p.add_argument("--duration", type=float, help="seconds of sequence to show (default: to the last tracked pose)")
    p.add_argument("--time", type=float, help="frame time for a .png, seconds (default: middle of the tracked range)")
    p.add_argument("--no-gt", action="store_true", help="do not draw the ground-truth contour")
    p.add_argument("--no-legend", action="store_true", help="no time and colour key in the frames")
    p.add_argument("--kernel-size", type=int, default=7, help="EROS window (odd, default 7)")
    p.add_argument("--decay", type=float, default=0.3, help="EROS decay d (default 0.3)")
    p.add_argument("--depth-jump", type=float, help="also draw internal depth edges deeper than this (metres)")
    p.add_argument("--poses-format", choices=FORMATS, help="override the pose format detection")
    p.add_argument("--poses-fps", type=float, help="frame rate giving the times of a BOP scene_gt.json")
    p.add_argument("--obj-id", type=int, help="object id to read from a BOP scene_gt.json")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run)
