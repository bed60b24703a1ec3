"""``torchevtrack benchmark BENCHDIR --out RESULTS``: the paper's ablations on a benchmark directory."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchevtrack.benchmark import METHODS, run_benchmark, table_markdown
from torchevtrack.cli.options import add_config_options, add_executor_options, config_from_args, executor_from_args


def _names(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected comma-separated names, got {text!r}")
    return names


def _noise(text: str) -> tuple[float, float]:
    try:
        mm, deg = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MM,DEG (two numbers), got {text!r}") from None
    return mm, deg


def _prediction(text: str) -> tuple[str, Path]:
    name, sep, directory = text.partition("=")
    if not sep or not name.strip() or not directory.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=DIR, got {text!r}")
    return name.strip(), Path(directory.strip())


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "benchmark",
        help="run the ablation benchmark on a directory of sequences",
        description="Track every sequence of BENCHDIR with each method (one batch per method and camera; with "
        "--executor process or ray, one task per sequence, method and draw), score other trackers' pose files "
        "(--pred) the same way, then write RESULTS/results.json, table.md (the paper's Table I), poses/, plots/ "
        "and overlays/, and print the table.",
    )
    p.add_argument("benchdir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--methods", type=_names, default=list(METHODS),
                   help=f"comma-separated methods (default: {','.join(METHODS)})")
    p.add_argument("--only", type=_names, help="comma-separated sequence names (default: all)")
    p.add_argument("--duration", type=float, help="track only the first SECONDS of each sequence")
    add_config_options(p)
    p.add_argument("--recover", action="store_true",
                   help="re-localise lost sequences and search once around each start, as track does (the loss "
                   "detector, recover.enabled and recover.start_search on; each search blocks ~0.3-1.5 s); the loss "
                   "table then counts the recoveries")
    p.add_argument("--textured", action="store_true",
                   help="track each printed object with its textured model (mesh_textured.glb, written by synth "
                   "--texture random) instead of mesh.ply, as with a textured scan; scored the same")
    p.add_argument("--no-overlays", action="store_true", help="skip the overlay PNGs and GIFs")
    p.add_argument("--no-batch", action="store_true", help="one run per sequence instead of one batch")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    p.add_argument("--init-noise", type=_noise, metavar="MM,DEG",
                   help="start each sequence MM millimetres and DEG degrees off its first ground-truth pose, in random "
                   "directions (a robustness test; see --trials)")
    p.add_argument("--trials", type=int, default=1,
                   help="draws of the perturbed start poses per method (default 1; > 1 needs --init-noise)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first draw (trial k: SEED + k; default 0)")
    p.add_argument("--pred", type=_prediction, action="append", default=[], metavar="NAME=DIR",
                   help="add another tracker as method NAME: its poses of sequence S in DIR/S.txt (or .csv, .json; "
                   "any format eval reads), scored as eval scores them; DIR/S.lost.txt, where present, its lost flags "
                   "for the loss table (repeatable)")
    add_executor_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _predictions(pairs: list[tuple[str, Path]]) -> dict[str, Path]:
    names = [n for n, _ in pairs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"--pred: method name(s) {dup} given more than once")
    return dict(pairs)


def run(args: argparse.Namespace) -> int:
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    cfg, predictions = config_from_args(args), _predictions(args.pred)
    with executor_from_args(args) as executor:
        res = run_benchmark(args.benchdir, args.out, methods=args.methods, only=args.only, duration_s=args.duration,
                            config=cfg, batch=not args.no_batch, overlays=not args.no_overlays,
                            progress=not args.quiet, init_noise=args.init_noise, trials=args.trials, seed=args.seed,
                            predictions=predictions, executor=executor, textured=args.textured)
    print(table_markdown(res), end="")
    from torchevtrack.report import write_suite_report

    factors, plot = write_suite_report(res, args.benchdir, args.out)
    print()
    print(factors.read_text(), end="")
    print(f"\nwritten: {args.out / 'results.json'}, {args.out / 'table.md'}, {factors}, {plot}")
    return 0
