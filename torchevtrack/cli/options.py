"""Command-line options shared by the commands that run the tracker: ``--config`` and ``--set``, ``--ablation``;
``--executor`` and ``--address`` for those that run many independent tracking tasks; ``--events`` (a recording in
any readable format beside a directory's ``camera.json``) for those that read a sequence's events."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.distortion import Undistorter
from torchevtrack.events import EventStream
from torchevtrack.io.formats import iter_events


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


def add_events_option(p: argparse.ArgumentParser, directory: str) -> None:
    """Add ``--events FILE`` (default: the sequence directory's events.h5) to parser ``p``."""
    p.add_argument("--events", type=Path, help="event file in any format `convert` reads (h5, npz, text, AEDAT4, "
                   f"EVT3, DSEC, YCB-Ev; detected from its content); default: {directory}/events.h5")


def events_path(args: argparse.Namespace, directory: Path) -> Path:
    """``--events``, else ``directory``'s events.h5; ``FileNotFoundError`` (one line) when neither is given."""
    if args.events is None and not (directory / "events.h5").is_file():
        raise FileNotFoundError(f"{directory} has no events.h5: give the event file with --events (any format "
                                "`convert` reads)")
    return args.events or directory / "events.h5"


def read_camera_events(path: Path, camera: Camera, undistort: bool = True, chunk: int = 1_000_000) -> EventStream:
    """Read an event file of any readable format (:func:`~torchevtrack.io.formats.iter_events`) ``chunk`` events at
    a time, checked against ``camera``'s sensor size; with ``undistort`` and a camera with distortion coefficients
    each chunk is moved into its pinhole image (:class:`~torchevtrack.distortion.Undistorter`) and the number of
    events that leave it is printed on stderr (stdout stays a command's output, e.g. ``bench --json``)."""
    chunks = iter_events(path, chunk_events=chunk, width=camera.width, height=camera.height)
    if not undistort or camera.distortion is None:
        return EventStream.concat(list(chunks))
    undistorter = Undistorter(camera)
    events = EventStream.concat([undistorter(c) for c in chunks])
    print(f"undistorted {len(events) + int(undistorter.dropped)} events, dropped {int(undistorter.dropped)} "
          "(outside the pinhole image)", file=sys.stderr)
    return events
