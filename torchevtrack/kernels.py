"""The numba kernels' on-disk cache: whether it is warm, a one-line notice when the first run will compile,
and :func:`warmup`, which compiles the tracker's kernels ahead (``torchevtrack warmup``).

Numba compiles a kernel on its first call in a process and caches the machine code in ``__pycache__``
next to the module (or in ``NUMBA_CACHE_DIR``); later processes load it in milliseconds. A fresh
install therefore spends its first tracking run compiling (about :data:`SECONDS_PER_KERNEL` seconds per kernel).

Each distinct argument type signature compiles a kernel again. Numba types a constant passed by a compiled caller
as a literal (``Literal[int](0)``, not ``int64``), so such call sites pass typed values (``np.int64(0)``,
``np.bool_(True)``) and optional arguments are given the same way from every caller: one signature per kernel.

Example:
    >>> from torchevtrack.kernels import uncached_kernels
    >>> isinstance(uncached_kernels(), list)
    True
"""

from __future__ import annotations

import sys
import threading

__all__ = ["SECONDS_PER_KERNEL", "announce_compile", "uncached_kernels", "warmup"]

SECONDS_PER_KERNEL = 1.6  # a first `track` from an empty cache compiles 90 kernels in 140 s (idle 2-core VM, README)
_announced = False


def _kernels() -> list:
    """The cached numba dispatchers of the loaded torchevtrack modules."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("torchevtrack.") and module is not None:
            for obj in list(vars(module).values()):
                if isinstance(obj, CPUDispatcher) and getattr(obj, "_cache", None) is not None:
                    found[id(obj)] = obj
    return list(found.values())


def _is_cached(kernel) -> bool:
    """Whether the cache holds compiled code for ``kernel`` from its current source (True if unknown)."""
    try:
        return bool(kernel._cache._cache_file._load_index())
    except Exception:  # numba's cache internals differ between versions: then assume cached, stay silent
        return True


def uncached_kernels() -> list[str]:
    """Names (``module.function``) of the loaded modules' kernels that the next run will compile: those of every
    module none of whose kernels has cached code for its current source (a fresh install, or an edited module).

    A module counts as a whole: its helper kernels, called only from its other kernels, are compiled into
    their callers and never get a cache entry of their own.
    """
    by_module: dict[str, list] = {}
    for k in _kernels():
        by_module.setdefault(k.py_func.__module__, []).append(k)
    return sorted(f"{m}.{k.py_func.__qualname__}" for m, ks in by_module.items()
                  if not any(_is_cached(k) for k in ks) for k in ks)


def announce_compile() -> None:
    """Print one line on stderr, once per process, if kernels of the loaded modules have no cached code."""
    global _announced
    if _announced:
        return
    missing = uncached_kernels()
    if missing:
        _announced = True
        wait = max(5, round(SECONDS_PER_KERNEL * len(missing) / 5) * 5)
        print(f"torchevtrack: compiling {len(missing)} numba kernels on first use (about {wait} s on a free core, "
              "once: cached afterwards; `torchevtrack warmup` does it ahead)", file=sys.stderr, flush=True)


def warmup(progress: bool = True) -> int:
    """Compile and cache the tracker's kernels by tracking a short built-in sequence (the box turning in front
    of a 160x120 camera, events at its silhouette's changes, optional stages on); returns the number of kernels
    compiled.

    A tqdm bar counts the kernels as their cache files appear.
    """
    global _announced
    import numpy as np
    import torch
    from tqdm import tqdm

    from torchevtrack.camera import Camera
    from torchevtrack.config import TrackerConfig
    from torchevtrack.events import EventStream
    from torchevtrack.mesh import load_mesh
    from torchevtrack.raster import RasterRenderer
    from torchevtrack.tracker import EventPoseTracker

    _announced = True  # this function reports its own progress
    camera = Camera(160, 120, 150.0, 150.0, 80.0, 60.0)
    mesh = load_mesh("box")
    missing = set(uncached_kernels())
    bar = tqdm(total=len(missing), unit="kernel", desc="compiling", disable=not progress or None)
    done = threading.Event()

    def follow():
        while not done.wait(0.5):
            bar.update(len(missing - set(uncached_kernels())) - bar.n)

    watcher = threading.Thread(target=follow, daemon=True)
    watcher.start()
    try:
        events, pose0 = _warmup_events(camera, mesh, RasterRenderer, EventStream, np, torch)
        # the optional denoise stage on too: its module loads with the tracker, and a cold one would be announced
        tracker = EventPoseTracker(camera, mesh, TrackerConfig().replace(denoise={"enabled": True}))
        tracker.track(events, pose0, progress=False)
        tracker.close()
        _compile_relocaliser(np)
        missing |= set(uncached_kernels())  # the modules the tracker loaded
    finally:
        done.set()
        watcher.join()
    compiled = len(missing - set(uncached_kernels()))
    bar.total = len(missing)
    bar.update(compiled - bar.n)
    bar.close()
    return compiled


def _compile_relocaliser(np) -> None:
    """Compile the re-localiser's edge and distance kernels (``--recover``), which a run that never loses the
    object does not call, on a tiny image."""
    from torchevtrack.chamfer import distance_map, model_edges

    depth = np.zeros((1, 8, 8), np.float32)
    depth[0, 2:6, 2:6] = 1.0
    distance_map(model_edges(depth, depth), 4.0)


def _warmup_events(camera, mesh, renderer_cls, stream_cls, np, torch):
    """Events where the box's silhouette changes between renders 2 ms apart over 60 ms, and its first pose."""
    steps = 31
    angle = np.linspace(0.0, 0.3, steps)
    poses = torch.zeros(steps, 7, dtype=torch.float64)
    poses[:, 0] = torch.from_numpy(np.linspace(-0.01, 0.01, steps))
    poses[:, 2] = 0.6
    poses[:, 3] = torch.from_numpy(np.cos(angle / 2))
    poses[:, 5] = torch.from_numpy(np.sin(angle / 2))
    with renderer_cls(mesh, camera) as r:
        inside = (r.render(poses).depth > 0).numpy()
    xs, ys, ts, ps = [], [], [], []
    for k in range(1, steps):
        change = inside[k] != inside[k - 1]
        y, x = np.nonzero(change)
        xs.append(x)
        ys.append(y)
        ts.append(np.linspace(2000 * (k - 1), 2000 * k - 1, len(x)).astype(np.int64))
        ps.append(inside[k][y, x].astype(np.int64))
    events = stream_cls.from_arrays(np.concatenate(xs), np.concatenate(ys), np.concatenate(ts), np.concatenate(ps),
                                    width=camera.width, height=camera.height)
    return events, poses[0]
