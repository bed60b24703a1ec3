"""``torchevtrack warmup``: compile the numba kernels into their on-disk cache ahead of the first run."""

from __future__ import annotations

import argparse


def run(args: argparse.Namespace) -> int:
    from torchevtrack.kernels import warmup

    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    warmup(progress=not args.quiet, jobs=args.jobs)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("warmup", help="compile and cache the numba kernels once (the first run otherwise does)",
                       description="Compile the tracker's numba kernels and cache them on disk (next to the "
                                   "package): in worker processes, one a core, then by tracking a short built-in "
                                   "sequence; later runs start at once.")
    p.add_argument("--jobs", type=int, default=None,
                   help="worker processes compiling at once (default: one per available core; 1: this process only)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
