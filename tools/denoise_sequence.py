"""Filter a sequence's events with the background-activity / hot-pixel filter and write a filtered copy.

Streams SEQDIR/events.h5 through :class:`~torchevtrack.stages.denoise.BackgroundActivityFilter` in chunks (its
state carries across them, as in a live stream) and writes OUTDIR with the kept events and the other files of
SEQDIR copied, so ``torchevtrack track`` and ``eval`` run on it unchanged. Prints the kept fraction and the
filter's speed (events/s of the filter call alone).

    python tools/denoise_sequence.py SEQDIR OUTDIR [--dt-us 10000]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import torch

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.io.events_h5 import EventsH5Writer, iter_events_h5
from torchevtrack.stages.denoise import BackgroundActivityFilter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir")
    ap.add_argument("outdir")
    ap.add_argument("--dt-us", type=int, default=10_000)
    ap.add_argument("--chunk", type=int, default=20_000, help="events per filter call (a 2 ms window is 2-10 k)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    src, dst = Path(args.seqdir), Path(args.outdir)
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("camera.json", "gt_poses.txt", "mesh.ply", "meta.json"):
        shutil.copy(src / name, dst / name)
    cam = Camera.load(src / "camera.json")
    f = BackgroundActivityFilter(cam.height, cam.width, dt_us=args.dt_us)
    f(torch.zeros(1, dtype=torch.int16), torch.zeros(1, dtype=torch.int16), torch.zeros(1, dtype=torch.int64))
    f.reset()  # (compiled now, not timed below)
    n_in = n_out = 0
    spent = 0.0
    tmp = dst / "events.h5.tmp"
    with EventsH5Writer(tmp, width=cam.width, height=cam.height) as w:
        for ev in iter_events_h5(src / "events.h5", chunk=1_000_000):
            for i in range(0, len(ev), args.chunk):
                e = ev[i:i + args.chunk]
                start = time.perf_counter()
                keep = f(e.x, e.y, e.t)
                spent += time.perf_counter() - start
                n_in += len(e)
                n_out += int(keep.sum())
                w.append(e.select(keep))
    tmp.replace(dst / "events.h5")
    print(f"{src} -> {dst}: kept {n_out} of {n_in} events ({100 * n_out / max(n_in, 1):.1f} %), "
          f"{int(f.hot.sum())} hot pixels; filter {n_in / spent / 1e6:.1f} M events/s")


if __name__ == "__main__":
    main()
