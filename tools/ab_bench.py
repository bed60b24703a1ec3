"""Speed of two revisions of torchevtrack, measured as alternating pairs of ``torchevtrack bench`` runs.

This machine's speed drifts by 25 % and more within minutes, so two trees are compared run for run: A, B, A, B, ...
Each revision is checked out into a temporary git worktree (removed at the end), warmed up once (numba compiles
and caches its kernels per tree), then each pair runs ``python -m torchevtrack bench SEQDIR --json`` in A's tree
and then in B's. Printed per figure: the median and range over the runs of each revision, and the median and
range of the paired ratios B / A (a ratio > 1: B is faster, or for latencies and stage times, slower).

    .venv/bin/python tools/ab_bench.py 5148949 HEAD --pairs 6 [--seq data/bench/mustard_fast] [--batch 8]

Revisions are anything ``git rev-parse`` takes; ``.`` is the working tree as it is (uncommitted changes
included). Run from the repository, with the project's virtual environment.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIGURES = {  # name: (path into the bench JSON, format)
    "streaming updates/s": (("updates_per_s",), "{:.0f}"),
    "latency p50 (ms)": (("p50_ms",), "{:.2f}"),
    "latency p99 (ms)": (("p99_ms",), "{:.2f}"),
    "offline updates/s": (("offline", "updates_per_s"), "{:.0f}"),
    "batch: sequence-updates/s": (("batched", "updates_per_s"), "{:.0f}"),
    "batch speed-up": (("batched_speedup",), "{:.2f}"),
    **{f"stage ms: {s}": (("stage_ms", s), "{:.3f}") for s in ("eros", "flow", "velocity", "render", "correction",
                                                               "ukf")},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="revision A (the reference)")
    ap.add_argument("b", help="revision B")
    ap.add_argument("--pairs", type=int, default=4, help="alternating pairs of runs (default 4)")
    ap.add_argument("--seq", type=Path, default=ROOT / "data" / "bench" / "mustard_fast", help="sequence directory")
    ap.add_argument("--duration", type=float, default=0.5, help="seconds tracked per run (default 0.5)")
    ap.add_argument("--batch", type=int, default=8, help="batch size of the batched measurement (default 8)")
    ap.add_argument("--config", type=Path, help="tracker config YAML for both revisions")
    ap.add_argument("--json", type=Path, help="also write every run's JSON here")
    args = ap.parse_args()
    if args.pairs < 1:
        ap.error(f"--pairs must be >= 1, got {args.pairs}")
    if not (args.seq / "events.h5").exists() and not args.seq.is_dir():
        ap.error(f"{args.seq} is not a sequence directory (make one: torchevtrack synth-benchmark --out data/bench)")

    bench = [str(args.seq.resolve()), "--json", "--threads", "1", "--duration", str(args.duration),
             "--batch", str(args.batch)] + (["--config", str(args.config.resolve())] if args.config else [])
    with tempfile.TemporaryDirectory(prefix="ab_bench_") as tmp:
        trees = [_tree(rev, Path(tmp) / name) for rev, name in ((args.a, "a"), (args.b, "b"))]
        try:
            for tree in trees:  # untimed: numba compiles and caches the tree's kernels
                _run(tree, [str(args.seq.resolve()), "--json", "--duration", "0.02", "--batch", "1"])
            runs: list[list[dict]] = [[], []]
            for i in range(args.pairs):
                for k, tree in enumerate(trees):
                    runs[k].append(_run(tree, bench))
                print(f"pair {i + 1}/{args.pairs}: streaming {runs[0][-1]['updates_per_s']:.0f} -> "
                      f"{runs[1][-1]['updates_per_s']:.0f} updates/s", file=sys.stderr)
        finally:
            for tree in trees:
                if tree != ROOT:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)
    if args.json:
        args.json.write_text(json.dumps({"a": args.a, "b": args.b, "runs_a": runs[0], "runs_b": runs[1]}, indent=1))
    print(_table(args.a, args.b, runs))


def _tree(rev: str, where: Path) -> Path:
    """A checkout of ``rev`` at ``where`` (a detached worktree), or the working tree itself for ``.``."""
    if rev == ".":
        return ROOT
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{rev}^{{commit}}"], check=True,
                            capture_output=True, text=True).stdout.strip()
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(where), commit], check=True)
    return where


def _run(tree: Path, bench_args: list[str]) -> dict:
    """One ``torchevtrack bench`` of the package in ``tree``: its JSON."""
    env = dict(os.environ, PYTHONPATH=str(tree), PYOPENGL_PLATFORM=os.environ.get("PYOPENGL_PLATFORM", "egl"))
    out = subprocess.run([sys.executable, "-m", "torchevtrack", "bench", *bench_args], cwd=tree, env=env,
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out)


def _get(run: dict, path: tuple[str, ...]):
    for key in path:
        run = run.get(key) if isinstance(run, dict) else None
    return run


def _table(a: str, b: str, runs: list[list[dict]]) -> str:
    rows = [f"| figure | A = {a}: median [range] | B = {b}: median [range] | B / A paired: median [range] |",
            "| --- | --- | --- | --- |"]
    for name, (path, fmt) in FIGURES.items():
        va, vb = ([_get(r, path) for r in rs] for rs in runs)
        if any(v is None for v in va + vb):
            continue
        cells = [f"{fmt.format(statistics.median(v))} [{fmt.format(min(v))} – {fmt.format(max(v))}]" for v in (va, vb)]
        ratios = [y / x for x, y in zip(va, vb) if x]
        cells.append(f"{statistics.median(ratios):.2f} [{min(ratios):.2f} – {max(ratios):.2f}]" if ratios else "–")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


if __name__ == "__main__":
    main()
