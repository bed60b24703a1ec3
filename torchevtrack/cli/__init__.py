"""The ``torchevtrack`` command. Each subcommand lives in a module of this package that exposes
``register(subparsers)``, which adds its parser(s) and sets ``func`` (args -> exit code).

Only the module of the command being run is imported (``torchevtrack --help`` and ``torchevtrack info``
do not pay for the tracker's imports): :data:`COMMANDS` names each command's module and its one-line help.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings

# command: (module in this package, help in `torchevtrack --help`), in the order --help shows them
COMMANDS: dict[str, tuple[str, str]] = {
    "objects": ("objects", "list the object names (built-in and YCB) that --object / --mesh accept"),
    "synth": ("synth", "simulate one synthetic event sequence"),
    "synth-benchmark": ("synth", "simulate the standard 8 benchmark sequences or a split of the wide suite"),
    "info": ("info", "summarise a sequence directory or an event file"),
    "track": ("track", "track the object of a sequence directory"),
    "live": ("live", "track a live event source (network stream, camera, paced recording)"),
    "eval": ("eval", "score predicted poses against ground truth"),
    "benchmark": ("benchmark", "run the ablation benchmark on a directory of sequences"),
    "bench": ("bench", "measure the tracker's speed on one sequence"),
    "viz": ("viz", "overlay video / image of mesh contours over the event surface"),
    "convert": ("convert", "convert an event file between formats (streamed)"),
    "demo": ("demo", "end-to-end demo on a synthetic sequence (no data needed)"),
    "warmup": ("warmup", "compile and cache the numba kernels once (the first run otherwise does)"),
}


def build_parser(command: str | None = None) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The parser and its commands' parsers by name: the full parser of ``command``'s module (if one of
    :data:`COMMANDS`), a one-line entry for the other commands."""
    parser = argparse.ArgumentParser(
        prog="torchevtrack", description="6D object pose tracking from events (learning-free, CPU)."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = COMMANDS[command][0] if command in COMMANDS else None
    for name, (module, help_text) in COMMANDS.items():
        if module != chosen:
            sub.add_parser(name, help=help_text)
        elif name == command:
            importlib.import_module(f"torchevtrack.cli.{module}").register(sub)
    return parser, sub.choices


def _command_of(argv: list[str]) -> str | None:
    """The first argument that is not an option: the command, if any."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser, commands = build_parser(_command_of(argv))
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # reported by the command's own parser: its usage line and name, not the top level's
        commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    with warnings.catch_warnings():  # warnings as one line each, like the errors (restored on return)
        warnings.showwarning = _one_line_warnings(args.command)
        try:
            return int(args.func(args) or 0)
        except (ValueError, FileNotFoundError, ImportError) as e:  # bad input, or an optional extra not installed
            print(f"torchevtrack {args.command}: error: {e}", file=sys.stderr)
            return 2


def _one_line_warnings(command: str):
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"torchevtrack {command}: warning: {message}", file=sys.stderr if file is None else file)
    return show


if __name__ == "__main__":
    sys.exit(main())
