"""Where an update's time goes: each compiled kernel, timed inside the running tracker, and the glue around them.

Wraps the tracker's numba kernels with wall-clock timers, tracks a benchmark sequence offline and prints the
microseconds per update of every kernel, their sum and the rest of ``forward`` (Python and tensor glue). The
kernels run with the caches the rest of the update leaves them (slower than in isolation, where
``tools/bench_template.py`` and ``tools/bench_raster.py`` time them).

    python tools/profile_update.py data/bench/mustard_fast --duration 0.5 --batch 1

With ``--batch B`` the sequence is tracked ``B`` times in one batch (``--workers`` threads; the kernel times are
then summed over the workers, so kernels + glue can exceed ``forward``). With one worker the tracker's pipeline
runs part of each update on a thread of its own (one stream: the next render and template, ``_render_model_kernel``,
and each window's EROS side and observation, ``_observe_kernel``; a batch: the next window's intake,
``_intake_kernel``), overlapping ``forward``; ``--no-pipeline`` runs everything inside.

``(wait for the intake thread)`` is the calling thread's time waiting for the pipeline's thread (counted with
the kernels, outside the glue).

``--stream`` pushes the events through an :class:`~torchevtrack.online.OnlineTracker` in 1 ms pushes, as
``torchevtrack bench`` does, and splits the kernels by thread: those of the calling thread (the rest of ``forward``
is its glue) and those of the pipeline's thread (``[intake]``); ``wall - forward`` is the time in the pushes outside
the tracker.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import threading
import time
from pathlib import Path

import torch

from torchevtrack.cli.bench import _stream, packets
from torchevtrack.config import TrackerConfig
from torchevtrack.kernels import warmup
from torchevtrack.online import OnlineTracker
from torchevtrack.schedule import Job
from torchevtrack import update
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker
from torchevtrack.update import RenderModelBinding

KERNELS = {
    "torchevtrack.stages.eros": ["eros_kernel", "_observe_kernel"],
    "torchevtrack.stages.flow": ["flow_packet"],
    "torchevtrack.update": ["_intake_kernel", "_motion_kernel", "_render_model_kernel", "canvas_kernel",
                            "_output_kernel"],
    "torchevtrack.raster": ["render_kernel"],
    "torchevtrack.stages.template": ["box_kernel", "model_kernel", "newton_kernel"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seqdir", type=Path)
    ap.add_argument("--duration", type=float, default=0.5, help="seconds tracked per pass (default 0.5)")
    ap.add_argument("--batch", type=int, default=1, help="copies of the sequence in one batch (default 1)")
    ap.add_argument("--workers", type=int, default=None, help="worker threads (default: the tracker's)")
    ap.add_argument("--no-pipeline", action="store_true", help="take each window in during its own update")
    ap.add_argument("--passes", type=int, default=3, help="timed passes after one warm-up pass (default 3)")
    ap.add_argument("--stream", action="store_true", help="push the events in 1 ms chunks (B = 1); kernels by thread")
    args = ap.parse_args()
    if args.stream and args.batch != 1:
        ap.error("--stream runs one sequence (--batch 1)")
    torch.set_num_threads(1)
    main_thread = threading.get_ident()

    # Compiled kernels call each other through module globals, which the timers replace: every kernel must be
    # compiled (or loaded from the cache) before, or one compiled afterwards cannot type its wrapped callee.
    warmup(progress=False)
    times: dict[str, float] = collections.defaultdict(float)
    for module, names in KERNELS.items():
        m = importlib.import_module(module)
        for name in names:
            def timed(*a, _f=getattr(m, name), _name=name):
                t = time.perf_counter()
                out = _f(*a)
                key = _name if not args.stream or threading.get_ident() == main_thread else f"[intake] {_name}"
                times[key] += time.perf_counter() - t
                return out
            setattr(m, name, timed)
    RenderModelBinding.kernel = staticmethod(update._render_model_kernel)  # the binding's own reference

    result = Job.result

    def timed_result(self):  # the calling thread waiting for the pipeline's thread
        t = time.perf_counter()
        out = result(self)
        if threading.get_ident() == main_thread:
            times["(wait for the intake thread)"] += time.perf_counter() - t
        return out

    Job.result = timed_result

    seq = Sequence.load(args.seqdir)
    t0 = int(seq.gt_t_us[0])
    t1 = min(int(seq.gt_t_us[-1]), t0 + round(args.duration * 1e6))
    tracker = EventPoseTracker(seq.camera, seq.mesh, TrackerConfig(), batch_size=args.batch, workers=args.workers,
                               pipeline=False if args.no_pipeline else None)
    forward = tracker.forward

    def timed_forward(*a, **k):
        t = time.perf_counter()
        out = forward(*a, **k)
        times["forward"] += time.perf_counter() - t
        return out

    tracker.forward = timed_forward
    rows = []
    for _ in range(args.passes + 1):
        times.clear()
        if args.stream:
            online = OnlineTracker(tracker)
            online.start(seq.gt_poses[0], t0)
            n = (t1 - t0) // tracker.period_us
            t1 = t0 + n * tracker.period_us
            pushes = packets(seq.events, t0, t1, 1000)
        start = time.perf_counter()
        if args.stream:
            _stream(online, pushes, t1)
        else:
            _, poses = tracker.track([seq.events] * args.batch, seq.gt_poses[0], t_start_us=t0, t_end_us=t1,
                                     progress=False)
            n = poses.shape[1]
        times["wall"] = time.perf_counter() - start
        rows.append({k: v / n * 1e6 for k, v in times.items()})
    tracker.close()
    best = min(rows[1:], key=lambda r: r["forward"])  # the pass least disturbed by the machine
    kernels = {k: v for k, v in best.items() if k not in ("forward", "wall")}
    mode = "streaming in 1 ms pushes" if args.stream else "offline"
    print(f"{args.seqdir.name}, {mode}, B = {args.batch}, {n} updates per pass; us per update (fastest of "
          f"{args.passes} passes):")
    for k, v in sorted(kernels.items(), key=lambda kv: (kv[0].startswith("["), -kv[1])):
        print(f"  {k:34s} {v:8.1f}")
    total = sum(v for k, v in kernels.items() if not k.startswith("["))  # the wait counts as a kernel here
    print(f"  {'kernels' + (' (calling thread)' if args.stream else ''):34s} {total:8.1f}\n"
          f"  {'glue (forward - kernels)':34s} {best['forward'] - total:8.1f}\n"
          f"  {'forward':34s} {best['forward']:8.1f}\n  {'wall':34s} {best['wall']:8.1f}")


if __name__ == "__main__":
    main()
