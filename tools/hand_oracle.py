"""The hand-held sequences of a suite, with the simulator's grip added to the tracker's model: the upper bound of
modelling a hand.

For every sequence directory under SRC (or SRC itself) whose ``meta.json`` says a hand holds the object
(``torchevtrack synth --occluder hand``), writes OUT/<name>/ whose ``mesh.ply`` is the object's mesh joined with the
grip (palm, fingers, thumb; not the forearm) that :func:`torchevtrack.synth.hand.make_hand` builds from that mesh, in
the object's frame, joined and coloured as the generator renders them (:func:`~torchevtrack.synth.hand.with_hand`: an
uncoloured object in the renderers' grey, the grip in skin); the other files are symbolic links to the sequence's.
The poses and the ground truth stay the object's, so ``torchevtrack benchmark OUT`` scores a tracker that knows the
hand's shape (docs/notebook.md, 2026-12-06: 33 of 64 dev hand runs held against 8). A sequence whose hand the mesh
does not reproduce (the forearm's end points in ``meta.json`` more than 1 mm from the rebuilt ones) is an error
(exit 2).

Example: ``python tools/hand_oracle.py data/wide_dev --out data/wide_dev_grip`` (then ``torchevtrack benchmark
data/wide_dev_grip --out R``)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from torchevtrack.synth.hand import make_hand, with_hand
from torchevtrack.synth.sequence import SEQUENCE_FILES

LINKED = tuple(name for name in SEQUENCE_FILES if name != "mesh.ply")  # the copy's own mesh.ply is written


def hand_sequences(src: Path) -> list[Path]:
    """The sequence directories at or under ``src`` (sorted by name) whose ``meta.json`` names a hand occluder."""
    dirs = [src] if (src / "meta.json").exists() else sorted(p for p in src.iterdir() if (p / "meta.json").exists())
    return [d for d in dirs if (json.loads((d / "meta.json").read_text()).get("occluder") or {}).get("kind") == "hand"]


def with_grip(seq: Path, out: Path) -> None:
    """Write ``out`` (see the module docstring) for the hand-held sequence ``seq``."""
    meta = json.loads((seq / "meta.json").read_text())
    mesh = trimesh.load(seq / "mesh.ply", force="mesh")
    hand = make_hand(mesh)
    off = float(np.abs(np.asarray(meta["occluder"]["forearm_segment_m"]) - hand.forearm_segment).max())
    if off > 1e-3:
        raise ValueError(f"{seq}: the mesh does not reproduce the sequence's hand (forearm {off * 1e3:.1f} mm off)")
    out.mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        link = out / name
        if not link.exists():
            link.symlink_to((seq / name).resolve())
    with_hand(mesh, dataclasses.replace(hand, forearm=trimesh.Trimesh())).export(out / "mesh.ply")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path, help="a suite directory or one sequence directory")
    ap.add_argument("--out", type=Path, required=True, help="directory for the copies (created)")
    args = ap.parse_args(argv)
    if not args.src.is_dir():
        print(f"error: {args.src} is not a directory", file=sys.stderr)
        return 2
    seqs = hand_sequences(args.src)
    if not seqs:
        print(f"error: no sequence with a hand under {args.src}", file=sys.stderr)
        return 2
    if args.out.resolve() in {s.resolve() for s in seqs} or args.out.resolve() == args.src.resolve():
        print("error: --out must not be the source", file=sys.stderr)
        return 2
    for seq in seqs:
        try:
            with_grip(seq, args.out / seq.name)
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
    print(f"{len(seqs)} sequences with a hand -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
