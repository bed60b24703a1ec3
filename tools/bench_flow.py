"""Per-window cost of the flow stage (:class:`~torchevtrack.stages.flow.TripletFlow`) on the tracker's workload.

Replays the 2 ms windows of a benchmark sequence, packed as the tracker packs them (int64 fields and a batch
index; ``--batch B`` packs ``B`` copies of the stream, copy ``k`` 50 ms later), through a TripletFlow with the
default config, single-threaded, and prints the process time per window (best and median of ``--repeat``
replays). ``--baseline REV`` also loads ``torchevtrack/stages/flow.py`` of git revision ``REV``, times it
interleaved with the working copy in the same process and compares every window's FlowField (max abs
difference, NaN-aware).

    .venv/bin/python tools/bench_flow.py [--seq data/bench/mustard_fast] [--batch 1] [--baseline HEAD]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchevtrack.benchmark import _prepare
from torchevtrack.config import TrackerConfig
from torchevtrack.stages import flow as flow_module
from torchevtrack.events import pack_streams

ROOT = Path(__file__).resolve().parents[1]


def windows(seq: Path, duration_s: float, batch: int, window_us: int = 2000):
    """Packed ``(x, y, t, p, b)`` windows and the sensor ``(H, W)``."""
    it = _prepare(seq, duration_s, window_us)
    ev = it.seq.events
    n = it.n_updates - (batch - 1) * 25
    k = torch.arange(n + 1, dtype=torch.int64) * window_us
    bounds = [torch.searchsorted(ev.t, it.t_start_us + j * 50_000 + k) for j in range(batch)]
    cam = it.seq.camera
    return [pack_streams([ev[int(bd[i]): int(bd[i + 1])] for bd in bounds]) for i in range(n)], (cam.height, cam.width)


def load_revision(rev: str):
    """``torchevtrack/stages/flow.py`` of git revision ``rev`` as a module of its own."""
    src = subprocess.run(["git", "show", f"{rev}:torchevtrack/stages/flow.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "flow_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("flow_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["flow_baseline"] = module
    spec.loader.exec_module(module)
    return module


def replay(flow, wins):
    flow.reset()
    return [flow(*w) for w in wins]


def max_difference(a, b) -> float:
    worst = 0.0
    for fa, fb in zip(a, b, strict=True):
        for u, v in zip(fa, fb):
            if u.dtype != v.dtype or u.shape != v.shape:
                return float("inf")
            if u.is_floating_point() and not torch.equal(u.isnan(), v.isnan()):
                return float("inf")
            if u.numel():
                worst = max(worst, float((u.double() - v.double()).nan_to_num().abs().max()))
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", type=Path, default=ROOT / "data/bench/mustard_fast")
    ap.add_argument("--duration", type=float, default=0.5, help="seconds of the sequence")
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--baseline", metavar="REV", help="git revision to compare with")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    wins, (H, W) = windows(a.seq, a.duration, a.batch)
    f = TrackerConfig().flow
    modules = {"working copy": flow_module}
    if a.baseline:
        modules[a.baseline] = load_revision(a.baseline)
    stages = {name: m.TripletFlow(H, W, batch_size=a.batch, block=f.block, min_samples=f.min_samples, D=f.radius,
                                  dt_max_us=f.dt_max_us, tol=f.tol, estimate=f.estimate)
              for name, m in modules.items()}
    outs = {name: replay(s, wins) for name, s in stages.items()}  # compiles
    times = {name: [] for name in stages}
    for _ in range(a.repeat):
        for name, s in stages.items():
            t0 = time.process_time()
            replay(s, wins)
            times[name].append((time.process_time() - t0) / len(wins))
    out = outs["working copy"]
    print(f"{a.seq.name} B={a.batch}: {len(wins)} windows, {np.mean([len(w[0]) for w in wins]):.0f} events, "
          f"{np.mean([int(o.count.sum()) for o in out]):.0f} samples each")
    for name, ts in times.items():
        print(f"  {name:<14s} best {min(ts) * 1e3:.3f} ms, median {np.median(ts) * 1e3:.3f} ms per window")
    if a.baseline:
        print(f"  max abs difference to {a.baseline}: {max_difference(out, outs[a.baseline]):.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
