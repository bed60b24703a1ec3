"""``torchevtrack bench SEQDIR [--batch B] [--duration S] [--json]``: tracker speed on one sequence.

SEQDIR is read as ``track`` reads it: a synthetic sequence as it is, or a recording with ``--events FILE`` (any
readable format), ``--mesh`` and ``--init`` (the speed of your own sensor's stream).

Three measurements in one run, each after a short untimed warm-up:

1. **streaming**: the events go through :class:`~torchevtrack.online.OnlineTracker` in pushes of
   ``--chunk-us`` of events (1 ms: what a sensor driver delivers; the packets are cut from the recording before
   the clock starts, as a driver hands them over), then a final flush. Gives updates/s, events/s, the real-time
   factor (tracked seconds / wall seconds), the per-update latency percentiles (from the push that completes a
   window to its pose) and the mean milliseconds of each stage (with the pipeline, the EROS side runs on its
   thread while the flow runs: the waits for it count in the stages that need it).
2. **one sequence offline**: :meth:`~torchevtrack.tracker.EventPoseTracker.track` with ``B = 1`` (pipelined with
   two or more cores, as the tracker's ``pipeline`` describes).
3. **batched** (``--batch B > 1``): ``B`` copies of the sequence in one batch. ``batched_speedup`` is
   ``B * (wall time of 2.) / (wall time of 3.)``: how much faster one batch is than ``B`` sequential runs.

With ``--repeat R`` the streaming and the offline runs are made ``R`` times each, alternating, so that both see the
same phases of a machine whose speed drifts: throughput and wall times are then the medians of the runs, the
latency percentiles those of all their updates together, the stage milliseconds means over all updates, and
``runs`` lists every run's figures. The batched case runs once and is compared with the median offline run.

The JSON also records the tracker ``config`` and the ``machine``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np
import torch

from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.online import OnlineTracker
from torchevtrack.tracker import EventPoseTracker
from torchevtrack.cli.options import add_ablation_option, add_config_options, config_from_args
from torchevtrack.cli.track import Recording, add_recording_options, load_recording

STAGES = ("eros", "flow", "velocity", "render", "correction", "ukf")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="measure the tracker's speed on one sequence",
        description="Track SEQDIR (a sequence directory) and report updates/s, events/s, the real-time factor, "
        "per-update latency (streaming pushes of --chunk-us of events), per-stage milliseconds and the speed-up "
        "of tracking --batch copies in one batch over sequential runs.",
    )
    add_recording_options(p)
    p.add_argument("--batch", type=int, default=4, help="batch size B of the batched measurement (1: skip it)")
    p.add_argument("--duration", type=float, help="track only the first SECONDS (default: the whole sequence)")
    add_ablation_option(p)
    add_config_options(p)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--chunk-us", type=int, default=1000, help="events per streaming push, microseconds (default 1000)")
    p.add_argument("--warmup", type=int, default=10, help="untimed updates before each measurement (default 10)")
    p.add_argument("--repeat", type=int, default=1,
                   help="streaming and offline runs, alternating; medians are reported (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    for name in ("batch", "threads", "chunk_us", "repeat"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.warmup < 0:
        raise ValueError(f"--warmup must be >= 0, got {args.warmup}")
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be positive, got {args.duration}")
    torch.set_num_threads(args.threads)
    recording = load_recording(args)
    cfg = config_from_args(args)
    result = bench(recording, cfg, batch=args.batch, duration_s=args.duration, chunk_us=args.chunk_us,
                   warmup=args.warmup, repeat=args.repeat)
    result = {"sequence": str(args.seqdir), "ablation": args.ablation or "default", **result}
    print(json.dumps(result, indent=2) if args.json else summary(result))
    return 0


def bench(recording: Recording, config: TrackerConfig, batch: int, duration_s: float | None = None,
          chunk_us: int = 1000, warmup: int = 10, repeat: int = 1) -> dict:
    """Run the three measurements (see the module docstring; streaming and offline ``repeat`` times each, alternating)
    from the recording's start pose and time, and return the numbers as a JSON-ready dict."""
    P = config.period_us
    t0, all_events = recording.t0_us, recording.events
    t_end = all_events.t_end if duration_s is None else min(t0 + round(duration_s * 1e6), all_events.t_end)
    n = (t_end - t0) // P
    if n < 1:
        raise ValueError(f"the sequence is shorter than one update period ({P} us) after t0 = {t0} us")
    t_end = t0 + n * P
    events = all_events.slice_time(t0, t_end)
    pose0 = recording.pose0
    warm_end = t0 + min(warmup, n) * P

    single = EventPoseTracker(recording.camera, recording.mesh, config)
    walls, offline_walls, latencies, stages = [], [], [], []
    try:
        online = OnlineTracker(single)
        for _ in range(repeat):
            if warmup:
                online.start(pose0, t0)
                _stream(online, packets(events, t0, warm_end, chunk_us), warm_end)
            online.start(pose0, t0)
            pushes = packets(events, t0, t_end, chunk_us)
            start = time.perf_counter()
            _stream(online, pushes, t_end)
            walls.append(time.perf_counter() - start)
            latencies.append(np.asarray(online.latencies_ms))  # one per update: n
            stages += online.stage_ms
            offline_walls.append(_timed_track(single, events, pose0, t0, t_end, warm_end, 1))
        pipeline = single.pipelined
    finally:
        single.close()

    wall, offline_wall = float(np.median(walls)), float(np.median(offline_walls))
    lat = np.concatenate(latencies)
    stage_ms = {s: float(np.mean([ms.get(s, 0.0) for ms in stages])) for s in STAGES}
    tracked_s = n * P / 1e6
    out = {
        "duration_s": tracked_s,
        "n_updates": n,
        "n_events": len(events),
        "period_us": P,
        "chunk_us": chunk_us,
        "wall_s": wall,
        "updates_per_s": n / wall,
        "events_per_s": len(events) / wall,
        "realtime_factor": tracked_s / wall,
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "latency_max_ms": float(lat.max()),
        "stage_ms": stage_ms,
        "update_ms": sum(stage_ms.values()),
        "offline": {"wall_s": offline_wall, "updates_per_s": n / offline_wall, "pipeline": pipeline},
        "repeat": repeat,
        "runs": {"updates_per_s": [n / w for w in walls], "p99_ms": [float(np.percentile(v, 99)) for v in latencies],
                 "offline_updates_per_s": [n / w for w in offline_walls]},
        "config": config.to_dict(),
        "batch": batch,
        "batched_speedup": None,
        "batched": None,
    }
    if batch > 1:
        batched = EventPoseTracker(recording.camera, [recording.mesh] * batch, config)
        try:
            batched_wall = _timed_track(batched, events, pose0, t0, t_end, warm_end, batch)
        finally:
            batched.close()
        sequential = batch * offline_wall
        out["batched_speedup"] = sequential / batched_wall
        out["batched"] = {"wall_s": batched_wall, "sequential_wall_s": sequential,
                          "updates_per_s": batch * n / batched_wall, "sequences": batch}
    out["machine"] = {
        "cpu_count": os.cpu_count(),
        "cpus_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "processor": platform.processor() or platform.machine(),
    }
    return out


def packets(events: EventStream, t0: int, t_end: int, chunk_us: int) -> list[EventStream]:
    """The events of ``[t0, t_end)`` cut into packets of ``chunk_us`` microseconds (views), as a driver delivers them."""
    return [events.slice_time(a, min(a + chunk_us, t_end)) for a in range(t0, t_end, chunk_us)]


def _stream(online: OnlineTracker, pushes: list[EventStream], t_end: int) -> None:
    """Push the packets, then flush ``t_end``."""
    for events in pushes:
        online.push(events)
    online.flush(t_end)


def _timed_track(tracker: EventPoseTracker, events: EventStream, pose0: torch.Tensor, t0: int, t_end: int,
                 warm_end: int, batch: int) -> float:
    """Wall seconds of the offline ``track`` of ``batch`` copies of ``events`` (after a warm-up run)."""
    if warm_end > t0:
        tracker.track([events] * batch, pose0, t_start_us=t0, t_end_us=warm_end, progress=False)
    start = time.perf_counter()
    tracker.track([events] * batch, pose0, t_start_us=t0, t_end_us=t_end, progress=False)
    return time.perf_counter() - start


def summary(r: dict) -> str:
    """A readable multi-line summary of :func:`bench`'s result."""
    m = r["machine"]
    lines = [
        f"{r['sequence']} ({r['ablation']}): {r['n_updates']} updates, {r['n_events']} events, "
        f"{r['duration_s']:.3f} s of events",
        f"streaming ({r['chunk_us']} us pushes): {r['updates_per_s']:.1f} updates/s, "
        f"{r['events_per_s'] / 1e6:.3f} Mev/s, real-time factor {r['realtime_factor']:.3f}",
        f"latency per update: p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms, max {r['latency_max_ms']:.1f} ms",
        "stage ms: " + ", ".join(f"{k} {v:.2f}" for k, v in r["stage_ms"].items()) + f" (sum {r['update_ms']:.1f})",
        f"offline, one sequence: {r['offline']['updates_per_s']:.1f} updates/s"
        + (" (pipelined: a second thread takes part of each update)" if r["offline"]["pipeline"] else ""),
    ]
    if r["repeat"] > 1:
        runs = r["runs"]
        lines.append(f"medians of {r['repeat']} runs; updates/s streaming "
                     f"{min(runs['updates_per_s']):.1f} - {max(runs['updates_per_s']):.1f}, offline "
                     f"{min(runs['offline_updates_per_s']):.1f} - {max(runs['offline_updates_per_s']):.1f}; latencies "
                     "over all runs")
    if r["batched"] is not None:
        b = r["batched"]
        lines.append(f"batch of {r['batch']}: {b['updates_per_s']:.1f} sequence-updates/s, "
                     f"speed-up over {r['batch']} sequential runs x{r['batched_speedup']:.2f}")
    lines.append(f"machine: {m['cpus_available']}/{m['cpu_count']} CPUs, {m['torch_threads']} torch threads, "
                 f"torch {m['torch']}, Python {m['python']}")
    return "\n".join(lines)
