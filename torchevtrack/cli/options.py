"""Command-line options shared by the commands that run the tracker: ``--config`` and ``--set``, ``--ablation``;
``--executor`` and ``--address`` for those that run many independent tracking tasks."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchevtrack.config import ABLATIONS, TrackerConfig


def add_config_options(p: argparse.ArgumentParser, default: str = "the built-in defaults") -> None:
    """Add ``--config YAML`` and the repeatable ``--set KEY=VALUE`` to parser ``p``."""
    p.add_argument("--config", type=Path, help=f"tracker config YAML (default: {default})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set",
                   help="change one config setting, dotted key typed by the config schema, e.g. --set "
                   "ukf.enabled=true --set eros.kernel_size=9 (repeatable; applied after --config)")


def add_ablation_option(p: argparse.ArgumentParser) -> None:
    """Add ``--ablation NAME`` (one of :data:`~torchevtrack.config.ABLATIONS`; none: the config as given)."""
    p.add_argument("--ablation", choices=sorted(ABLATIONS),
                   help="one of the paper's methods (full: with its UKF; no_ukf: without it, as the default config), "
                   "or hypotheses: the full method and its twin without the UKF, the better of the two (about 2.3x the "
                   "time); default: the config as given")


def config_from_args(args: argparse.Namespace) -> TrackerConfig:
    """The :class:`TrackerConfig` of ``--config`` (or the defaults), with the loss detector, recovery and the start
    search on for a command's ``--recover``, then the ``--set`` changes applied (so ``--set recover.KEY=...`` may refine
    ``--recover``), then a command's ``--ablation``, if given."""
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    if getattr(args, "recover", False):
        cfg = cfg.replace(loss={"enabled": True}, recover={"enabled": True, "start_search": True})
    cfg = cfg.override(args.set) if args.set else cfg
    ablation = getattr(args, "ablation", None)
    return cfg.replace(**ABLATIONS[ablation]) if ablation else cfg


def add_executor_options(p: argparse.ArgumentParser, default: str = "serial") -> None:
    """Add ``--executor serial|process|ray`` (default ``default``), ``--jobs N`` and ``--address ADDR`` to
    parser ``p``."""
    from torchevtrack.executor import EXECUTORS

    p.add_argument("--executor", choices=EXECUTORS, default=default,
                   help=f"where the independent tasks run: one after the other here, a local process pool, or Ray "
                   f"tasks (a local Ray without --address); the results are the same (default: {default})")
    p.add_argument("--jobs", type=int, help="processes of --executor process, CPUs of a local Ray "
                   "(default: the usable cores)")
    p.add_argument("--address", help="Ray cluster to run on with --executor ray: auto, HOST:6379 or ray://HOST:10001 "
                   "(default: start a local Ray)")


def executor_from_args(args: argparse.Namespace):
    """The :class:`~torchevtrack.executor.Executor` of ``--executor``, ``--jobs`` and ``--address``."""
    from torchevtrack.executor import make_executor

    return make_executor(args.executor, workers=args.jobs, address=args.address)
