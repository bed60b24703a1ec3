"""``torchevtrack benchmark BENCHDIR --out RESULTS``: the paper's ablations on a benchmark directory."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchevtrack.benchmark import METHODS, run_benchmark, table_markdown


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


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "benchmark",
        help="run the ablation benchmark on a directory of sequences",
        description="Track every sequence of BENCHDIR with each method (one batch per method and camera), then "
        "write RESULTS/results.json, table.md (the paper's Table I), poses/, plots/ and overlays/, and print "
        "the table.",
    )
    p.add_argument("benchdir", type=Path)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--methods", type=_names, default=list(METHODS),
                   help=f"comma-separated methods (default: {','.join(METHODS)})")
    p.add_argument("--only", type=_names, help="comma-separated sequence names (default: all)")
    p.add_argument("--duration", type=float, help="track only the first SECONDS of each sequence")
    p.add_argument("--config", type=Path, help="tracker config YAML (default: the built-in defaults)")
    p.add_argument("--no-overlays", action="store_true", help="skip the overlay PNGs and GIFs")
    p.add_argument("--no-batch", action="store_true", help="one run per sequence instead of one batch")
    p.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    p.add_argument("--init-noise", type=_noise, metavar="MM,DEG",
                   help="start each sequence MM millimetres and DEG degrees off its first ground-truth pose, in random "
                   "directions (a robustness test; see --trials)")
    p.add_argument("--trials", type=int, default=1,
                   help="draws of the perturbed start poses per method (default 1; > 1 needs --init-noise)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first draw (trial k: SEED + k; default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.threads is not None:
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    res = run_benchmark(args.benchdir, args.out, methods=args.methods, only=args.only, duration_s=args.duration,
                        config=args.config, batch=not args.no_batch, overlays=not args.no_overlays,
                        progress=not args.quiet, init_noise=args.init_noise, trials=args.trials, seed=args.seed)
    print(table_markdown(res), end="")
    from torchevtrack.report import write_suite_report

    factors, plot = write_suite_report(res, args.benchdir, args.out)
    print()
    print(factors.read_text(), end="")
    print(f"\nwritten: {args.out / 'results.json'}, {args.out / 'table.md'}, {factors}, {plot}")
    return 0
