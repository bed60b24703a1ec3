"""Command-line options shared by the commands that run the tracker: ``--config`` and ``--set``."""

from __future__ import annotations

import argparse
from pathlib import Path

from torchevtrack.config import TrackerConfig


def add_config_options(p: argparse.ArgumentParser, default: str = "the built-in defaults") -> None:
    """Add ``--config YAML`` and the repeatable ``--set KEY=VALUE`` to parser ``p``."""
    p.add_argument("--config", type=Path, help=f"tracker config YAML (default: {default})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set",
                   help="change one config setting, dotted key typed by the config schema, e.g. --set ukf.enabled=false "
                   "--set eros.kernel_size=9 (repeatable; applied after --config)")


def config_from_args(args: argparse.Namespace) -> TrackerConfig:
    """The :class:`TrackerConfig` of ``--config`` (or the defaults) with the ``--set`` changes applied."""
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    return cfg.override(args.set) if args.set else cfg
