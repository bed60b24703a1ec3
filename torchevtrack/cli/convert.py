"""``torchevtrack convert IN OUT``: stream events from any readable format into events.h5, npz or text."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from torchevtrack.io.formats import FORMATS, WRITABLE, open_events, write_events


def run(args: argparse.Namespace) -> int:
    try:
        return _convert(args)
    except ImportError as e:  # an optional reader package is missing: the message has the install hint
        print(f"torchevtrack convert: error: {e}", file=sys.stderr)
        return 2


def _convert(args: argparse.Namespace) -> int:
    src, dst = Path(args.input), Path(args.output)
    if dst.exists() and dst.resolve() == src.resolve():
        raise ValueError(f"output {dst} is the input file")
    if (args.width is None) != (args.height is None):
        raise ValueError("give --width and --height together")
    ef = open_events(src, args.in_format, chunk_events=args.chunk, width=args.width, height=args.height,
                     sort=args.sort, drop_out_of_bounds=args.drop_out_of_bounds)
    by_bytes = ef.bytes_read is not None
    bar = tqdm(total=ef.size_bytes if by_bytes else None, unit="B" if by_bytes else "ev", unit_scale=True,
               desc=f"{src.name} -> {dst.name}", disable=args.quiet or None)
    span = [None, None]

    def chunks():
        for ev in ef:
            span[0] = int(ev.t[0]) if span[0] is None else span[0]
            span[1] = int(ev.t[-1])
            if by_bytes:
                bar.update(ef.bytes_read - bar.n)
            else:
                bar.update(len(ev))
            yield ev

    with bar:
        n = write_events(dst, chunks(), args.out_format, width=ef.width, height=ef.height)
    if not args.quiet:
        t = f", t {span[0]} .. {span[1]} us" if n else ""
        print(f"wrote {n} events ({ef.format} -> {args.out_format or dst.suffix.lstrip('.')}{t}) to {dst}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("convert", help="convert an event file between formats (streamed)",
                              description="Read events from any supported format (detected from the file "
                                          "unless --in-format) and write events.h5, npz or text, chunk by "
                                          "chunk, validating time order and sensor bounds.")
    p.add_argument("input", help="input event file")
    p.add_argument("output", help="output file (.h5/.hdf5, .npz, .txt/.csv, or set --out-format)")
    p.add_argument("--in-format", choices=FORMATS, help="input format (default: detected)")
    p.add_argument("--out-format", choices=WRITABLE, help="output format (default: from the extension)")
    p.add_argument("--chunk", type=int, default=1_000_000, help="events per chunk (default 1e6)")
    p.add_argument("--sort", action="store_true", help="sort by time (reads the whole input into memory)")
    p.add_argument("--width", type=int, help="sensor width: events must have x < W")
    p.add_argument("--height", type=int, help="sensor height: events must have y < H")
    p.add_argument("--drop-out-of-bounds", action="store_true", help="drop events outside --width/--height")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run)
