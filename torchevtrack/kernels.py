"""The numba kernels' on-disk cache: whether it is warm, compiling it in parallel worker processes when it is cold
(:func:`compile_cold`, on a tracker's first construction), and :func:`warmup`, which compiles the tracker's kernels
ahead (``torchevtrack warmup``).

Numba compiles a kernel on its first call in a process and caches the machine code in ``__pycache__``
next to the module (or in ``NUMBA_CACHE_DIR``); later processes load it in milliseconds. A fresh
install therefore compiles before its first pose: about 150 s of one core for the kernels a tracking run calls.
Compilation holds one core, so :func:`compile_cold` spreads the kernels over worker processes, one a core, each
compiling kernels named in the shipped manifest ``kernels.json`` (each kernel called from Python, the argument
types a tracking run calls it with, and its measured compile time) into the shared cache, largest first; the
tracking process then loads them. A kernel the manifest misses (or that a worker failed on) still compiles on its
first call, as before: the manifest only saves time. ``python tools/kernel_manifest.py`` writes it anew.

A process computes the same whether it compiled a kernel or loaded it from the cache. Numba links a copy of each
compiled callee into its caller and optimises it again; a process that compiled the callee runs the callee's own code,
one that loaded the caller runs the copy. The two compute alike unless the callee's ``fastmath`` flags let LLVM change
its results (reassociation, contraction, approximate division or functions: any flag beyond
:data:`EXACT_FASTMATH`), so a kernel with such flags is called only from Python or inlined into its callers
(``inline="always"``: each caller compiles it under its own flags), unless its rounding only widens bounds that hold
in any order (the flow's ``_spread_sums``); ``tests/test_kernels.py`` checks both. And every kernel is compiled
with :func:`kernel`, which states its ``fastmath`` flags and error model: numba would otherwise give a kernel its
first compiling caller's, so that the cached code depended on which caller a process compiled first.

Each distinct argument type signature compiles a kernel again. Numba types a constant passed by a compiled caller
as a literal (``Literal[int](0)``, not ``int64``), so such call sites pass typed values (``np.int64(0)``,
``np.bool_(True)``) and optional arguments are given the same way from every caller: one signature per kernel.

Example:
    >>> from torchevtrack.kernels import uncached_kernels
    >>> isinstance(uncached_kernels(), list)
    True
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import selectors
import subprocess
import sys
import threading
from importlib import import_module
from pathlib import Path

__all__ = ["ANY_ORDER_FASTMATH", "EXACT_FASTMATH", "compile_cold", "decode_signature", "encode_signature",
           "drop_stale_callers", "kernel", "load", "loaded_signatures", "manifest", "uncached_kernels", "warmup"]

MANIFEST = Path(__file__).with_name("kernels.json")
EXACT_FASTMATH = {"nnan", "ninf", "nsz"}
"""The ``fastmath`` flags that leave a kernel's results on finite numbers as they are, whatever LLVM makes of it
(the flags of a kernel that other kernels call; a set, as numba takes it: never mutated)."""
ANY_ORDER_FASTMATH = {"reassoc", "nsz", "arcp", "contract", "afn"}
"""The ``fastmath`` flags of a kernel that sums in any order (in vector lanes), with NaN and infinity kept: for a
kernel called only from Python, or inlined into its callers."""


def kernel(fn=None, *, fastmath=False, error_model="python", inline="never"):
    """``numba.njit`` as every kernel of the package is compiled: cached on disk, without the GIL, and with its own
    ``fastmath`` flags and error model, never a caller's (``@kernel`` or ``@kernel(fastmath=...)``).

    Numba compiles a kernel that a caller's compilation reaches first with the caller's ``fastmath`` and
    ``error_model`` wherever the kernel leaves them unset, and caches its code by argument types only: which caller a
    process happened to compile first (the order of :func:`compile_cold`'s workers) then decided for every later
    process whether, say, :func:`torchevtrack.linalg.eigh` summed in any order, and two fresh installs of the same
    source tracked differently. Stated on every kernel, both flags are the kernel's own whatever the order
    (``tests/test_kernels.py``).

    Example:
        >>> from torchevtrack.linalg import eigh  # @kernel
        >>> eigh.targetoptions["fastmath"], eigh.targetoptions["error_model"]
        (False, 'python')
    """
    import numba

    options = {"cache": True, "nogil": True, "fastmath": fastmath, "error_model": error_model, "inline": inline}
    return numba.njit(**options) if fn is None else numba.njit(**options)(fn)


SECONDS_PER_KERNEL = 1.6  # a kernel's compile time on average (150 s for the ~90 of a tracking run, idle 2-core VM)
_lock = threading.Lock()
_tried = False  # compile_cold ran in this process: it announces and compiles at most once


# -- callers of an edited module: numba keys a kernel's cache on its own file only --------------------------------
def _package_modules(root: Path, package: str) -> dict[str, Path]:
    """Every module of the package in ``root``: ``{dotted name: file}``."""
    out = {}
    for f in sorted(root.rglob("*.py")):
        parts = f.relative_to(root).with_suffix("").parts
        out[".".join((package, *(parts[:-1] if parts[-1] == "__init__" else parts)))] = f
    return out


def _imports(source: str, modules: dict[str, Path], package: str) -> set[str]:
    """The package's modules that ``source`` imports anywhere (top level or inside functions); none if it does
    not parse."""
    import ast  # only after an edit: not on every import

    try:
        tree = ast.parse(source)
    except SyntaxError:
        return set()
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)  # `from pkg.sub import module`
    return {m for m in found if m == package or m.startswith(package + ".")} & set(modules)


def _cache_dir(file: Path) -> Path:
    """Where numba caches the kernels of ``file``: ``NUMBA_CACHE_DIR``'s subdirectory for the file's directory (as
    numba names it), else the ``__pycache__`` beside it."""
    user = os.environ.get("NUMBA_CACHE_DIR")
    if not user:
        return file.parent / "__pycache__"
    folder = os.path.dirname(os.path.abspath(file))
    return Path(user) / f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"


def drop_stale_callers(root: Path | None = None, package: str = "torchevtrack") -> list[str]:
    """Delete the cached kernels of every module that imports, directly or through others, a module of the package
    whose source changed since the last call; returns those modules' names (sorted).

    Numba keys a kernel's cache on its own source file only, so a kernel that calls a compiled function of another
    module keeps the machine code of that function's old source after it is edited (numba issue 1833): an edit to
    ``stages/template.py`` would not reach the steps of ``update.py`` that call it. This runs on ``import
    torchevtrack``: a stat of each source file when nothing changed (the record of sizes, times and content hashes
    is a JSON file in the cache directory); after an edit the importers' kernels compile again on first call. With
    no record (a first run, or a cache written before this check) every module that imports another is stale. Cache
    problems (a read-only install, a race with
    another process) are ignored: numba then uses what it has, as it would without this.

    Example:
        >>> drop_stale_callers()  # nothing edited since the last import
        []
    """
    root = Path(__file__).parent if root is None else Path(root)
    record = _cache_dir(root / "__init__.py") / f"{package}-sources.json"
    modules = _package_modules(root, package)
    stats = {m: [st.st_mtime_ns, st.st_size] for m, st in ((m, f.stat()) for m, f in modules.items())}
    try:
        old = json.loads(record.read_text())
    except (OSError, ValueError):
        old = {}
    if old.get("stats") == stats:
        return []
    texts = {m: f.read_bytes() for m, f in modules.items()}
    hashes = {m: hashlib.sha1(t).hexdigest() for m, t in texts.items()}
    graph = {m: _imports(t.decode("utf-8", "replace"), modules, package) for m, t in texts.items()}
    if "hashes" in old:
        edited = {m for m in set(hashes) | set(old["hashes"]) if old["hashes"].get(m) != hashes.get(m)}
    else:  # no record: any module that imports another may hold code of an edit made before
        edited = {m for m, deps in graph.items() if deps - {m}}
    stale, grew = set(edited), True
    while grew:  # every module that reaches an edited one through imports
        new = {m for m, deps in graph.items() if m not in stale and deps & stale}
        stale |= new
        grew = bool(new)
    dropped = []
    for m in sorted(stale & set(modules)):
        if m in edited and "hashes" in old:
            continue  # numba sees its own source changed
        stem = modules[m].stem
        files = list(_cache_dir(modules[m]).glob(f"{stem}.*.nb[ic]"))
        for f in files:
            with contextlib.suppress(OSError):
                f.unlink()
        if files:
            dropped.append(m)
    with contextlib.suppress(OSError):
        record.parent.mkdir(parents=True, exist_ok=True)
        tmp = record.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"stats": stats, "hashes": hashes}))
        os.replace(tmp, record)
    return dropped


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


# -- the manifest: which kernels a tracking run calls from Python, with which argument types ------------------
def encode_signature(sig) -> list:
    """A numba argument-type tuple as JSON-ready values: ``["array", dtype, ndim, layout, readonly]`` for an array,
    the type's name for a scalar or ``none``, ``["tuple", "module:Class", [fields...]]`` for a named tuple.

    Raises:
        ValueError: a type of another kind (the manifest's reader would not rebuild it).

    Example:
        >>> from numba import types
        >>> encode_signature((types.Array(types.float64, 2, "C", readonly=True), types.int64, types.none))
        [['array', 'float64', 2, 'C', True], 'int64', 'none']
    """
    from numba.core import types

    def one(t):
        if isinstance(t, types.Array) and t.aligned:
            return ["array", str(t.dtype), t.ndim, t.layout, not t.mutable]
        if isinstance(t, types.BaseNamedTuple):
            return ["tuple", f"{t.instance_class.__module__}:{t.instance_class.__qualname__}", [one(f) for f in t]]
        if isinstance(t, (types.Number, types.Boolean, types.NoneType)):
            return str(t)
        raise ValueError(f"kernel manifest: cannot encode argument type {t!r}")

    return [one(t) for t in sig]


def decode_signature(values: list) -> tuple:
    """The numba argument-type tuple of :func:`encode_signature`'s ``values`` (its inverse).

    Example:
        >>> sig = decode_signature([["array", "float32", 3, "C", False], "bool", "float64"])
        >>> encode_signature(sig)
        [['array', 'float32', 3, 'C', False], 'bool', 'float64']
    """
    from numba.core import types

    def one(v):
        if isinstance(v, str):
            return types.boolean if v == "bool" else getattr(types, v)
        if v[0] == "array":
            return types.Array(one(v[1]), v[2], v[3], readonly=v[4])
        module, cls = v[1].split(":")
        return types.BaseTuple.from_types([one(f) for f in v[2]], getattr(import_module(module), cls))

    return tuple(one(v) for v in values)


def loaded_signatures() -> list[tuple[str, list]]:
    """``(module.function, encoded signature)`` of every signature this process compiled or loaded from the cache,
    for the kernels of the loaded modules. After a run from a warm cache these are the calls from Python (code
    loaded from the cache types no callee): what the manifest lists."""
    return sorted(((f"{k.py_func.__module__}.{k.py_func.__qualname__}", encode_signature(s))
                   for k in _kernels() for s in k.signatures), key=json.dumps)


def manifest() -> list[dict]:
    """The shipped manifest: ``[{"name": "module.function", "signature": [...], "seconds": s}, ...]``, largest
    compile time first (``seconds``: one core of the machine that wrote it, callees included); empty while
    ``tools/kernel_manifest.py`` writes it (the kernels then compile on first call)."""
    return json.loads(MANIFEST.read_text())["kernels"] if MANIFEST.exists() else []


def load() -> int:
    """Load every kernel of the manifest into this process (from the cache; compiling an entry it does not hold), so
    that no later call waits for one: a stream's first updates otherwise load their kernels as they first call them
    (at 1280x720 the longest of the first 50 pushes took 16-26 ms instead of 5-6 ms). About 0.6 s from a warm cache.
    Returns the entries loaded."""
    entries = manifest()
    for entry in entries:
        _compile_entry(entry)
    return len(entries)


# -- compiling in worker processes --------------------------------------------------------------------------------
def _compile_entry(entry: dict) -> None:
    """Compile (or load from the cache) one manifest entry in this process."""
    module, name = entry["name"].rsplit(".", 1)
    getattr(import_module(module), name).compile(decode_signature(entry["signature"]))


def _worker() -> None:
    """A compile worker (``python -m torchevtrack.kernels``): reads manifest indices from stdin, one a line,
    compiles each and answers ``compiled INDEX`` (or ``failed INDEX``) on stdout."""
    entries = manifest()
    for line in sys.stdin:
        i = int(line)
        try:
            _compile_entry(entries[i])
            print("compiled", i, flush=True)
        except Exception:  # the tracking process compiles it on first call, and reports the error there
            print("failed", i, flush=True)


def _cores() -> int:
    """The cores worker processes may use: those available to this process, or none where ``sys.executable`` is no
    Python interpreter (a frozen application, or one that embeds Python) to start them with."""
    if getattr(sys, "frozen", False) or not Path(sys.executable or "").name.lower().startswith("python"):
        return 1
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _compile_in_workers(entries: list[int], jobs: int, on_done=None) -> int:
    """Compile manifest ``entries`` (indices, largest first) in ``jobs`` worker processes, each taking the next
    entry when it is free; calls ``on_done()`` after each. Returns how many compiled. Workers that cannot start
    or fail leave their kernels to their first call; an interrupt stops them at once."""
    pending = list(entries)
    workers = []
    done = 0
    sel = selectors.DefaultSelector()
    try:
        for _ in range(min(jobs, len(pending))):
            w = subprocess.Popen([sys.executable, "-m", "torchevtrack.kernels"], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
            workers.append(w)
            w.stdin.write(f"{pending.pop(0)}\n")
            sel.register(w.stdout, selectors.EVENT_READ, w)
        while sel.get_map():
            for key, _ in sel.select():
                w, line = key.data, key.fileobj.readline()
                answer = line.split()[:1]
                if not line:  # the worker ended: what it held is left to the first call
                    sel.unregister(key.fileobj)
                elif answer in (["compiled"], ["failed"]):  # (other output of the worker's imports: not an answer)
                    done += answer == ["compiled"]
                    if on_done is not None:
                        on_done()
                    if pending:
                        w.stdin.write(f"{pending.pop(0)}\n")
                    else:
                        sel.unregister(key.fileobj)
    except OSError:  # a worker could not start or its pipe broke: the rest compiles on first call
        pass
    except BaseException:
        for w in workers:
            w.kill()
        raise
    finally:
        for w in workers:
            with contextlib.suppress(OSError):
                w.stdin.close()
            w.wait()
        sel.close()
    return done


def compile_cold(progress: bool = False, jobs: int | None = None) -> int:
    """If the loaded modules have uncached kernels: say so on stderr in one line and compile the manifest's kernels
    of those modules in ``jobs`` worker processes (default: one per available core, but no more than the total
    compile time over the largest kernel's, which bounds the wall time; with one, nothing is compiled ahead and the
    kernels compile on first call). Returns how many compiled. Acts once per process (later calls return 0; what
    is still cold compiles on first call); thread-safe; processes starting cold at once take turns on a lock file
    in the cache directory, so the kernels compile once.

    The tracker calls it when it is built, so a fresh install's first run waits about the manifest's compile time
    divided by the cores, not the sum.
    """
    return _compile_cold(progress, jobs, announce=True)


@contextlib.contextmanager
def _cache_lock():
    """Hold an exclusive lock on a file in the kernels' cache directory (POSIX ``flock``; elsewhere, or where the
    file cannot be opened, no lock), so that processes starting cold at once (Ray workers) compile once: the first
    compiles, the others wait, then find the cache warm. Says so on stderr when it has to wait."""
    from torchevtrack.events import first_invalid

    try:
        import fcntl

        f = open(Path(first_invalid.stats.cache_path) / "torchevtrack-compile.lock", "a")
    except (ImportError, OSError):
        yield
        return
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            print("torchevtrack: another process is compiling the numba kernels; waiting for it", file=sys.stderr,
                  flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _compile_cold(progress: bool, jobs: int | None, announce: bool) -> int:
    global _tried
    with _lock:
        if _tried:
            return 0
        _tried = True
        if not uncached_kernels():
            return 0
        with _cache_lock():
            return _compile_missing(progress, jobs, announce)


def _compile_missing(progress: bool, jobs: int | None, announce: bool) -> int:
    missing = set(uncached_kernels())  # again: a process that held the lock may have compiled them
    if not missing:
        return 0
    listed = manifest()
    entries = [i for i, e in enumerate(listed) if e["name"] in missing]
    seconds = [listed[i]["seconds"] for i in entries] or [SECONDS_PER_KERNEL * len(missing)]
    if jobs is None:
        jobs = min(_cores(), math.ceil(sum(seconds) / max(max(seconds), 1e-3)))
    jobs = min(jobs, len(entries))
    if announce:
        wait = max(sum(seconds) / max(jobs, 1), max(seconds))
        how = f"in {jobs} processes " if jobs > 1 else ""
        print(f"torchevtrack: compiling {len(missing)} numba kernels on first use {how}(about "
              f"{max(5, round(wait / 5) * 5)} s, once: cached afterwards; `torchevtrack warmup` does it ahead)",
              file=sys.stderr, flush=True)
    if jobs < 2:
        return 0
    from tqdm import tqdm

    with tqdm(total=len(entries), unit="kernel", desc="compiling", disable=not progress or None) as bar:
        return _compile_in_workers(entries, jobs, on_done=lambda: bar.update(1))


def warmup(progress: bool = True, jobs: int | None = None) -> int:
    """Compile and cache the tracker's kernels: the manifest's in ``jobs`` worker processes (:func:`compile_cold`;
    default one per available core, a tqdm bar counting them), then by tracking a short built-in sequence (the box
    turning in front of a 160x120 camera, events at its silhouette's changes, optional stages on), which loads them
    and compiles whatever the manifest misses. Returns the number of kernels that were uncached.
    """
    import numpy as np
    import torch

    from torchevtrack.camera import Camera
    from torchevtrack.config import TrackerConfig
    from torchevtrack.events import EventStream
    from torchevtrack.mesh import load_mesh
    from torchevtrack.raster import RasterRenderer
    from torchevtrack.tracker import EventPoseTracker

    missing = set(uncached_kernels())
    _compile_cold(progress, jobs, announce=False)  # its bar says it; the tracker's own call below finds it done
    camera = Camera(160, 120, 150.0, 150.0, 80.0, 60.0)
    mesh = load_mesh("box")
    events, pose0 = _warmup_events(camera, mesh, RasterRenderer, EventStream, np, torch)
    # the optional stages on too (denoise, loss detector, recovery and its start search, the UKF): their modules load
    # with the tracker, and a cold kernel would be announced; then the defaults (the output step without the UKF)
    optional = TrackerConfig().replace(denoise={"enabled": True}, loss={"enabled": True},
                                       recover={"enabled": True, "start_search": True}, ukf={"enabled": True})
    for cfg in (optional, TrackerConfig()):
        tracker = EventPoseTracker(camera, mesh, cfg)
        times, _ = tracker.track(events, pose0, progress=False)
        if cfg.recover.start_search:  # a start search whose chamfer result does not win refines turned poses
            tracker.refine(tracker.pose[:1], 0, int(times[0, -1]))
        tracker.close()
    _compile_relocaliser(np)
    return len(missing - set(uncached_kernels()))


def _compile_relocaliser(np) -> None:
    """Compile the re-localiser's event, edge and distance kernels (``--recover``, ``hypotheses``), which a run
    that never loses the object does not call, on a tiny image."""
    import torch

    from torchevtrack.chamfer import distance_map, model_edges, recent_events

    depth = np.zeros((1, 8, 8), np.float32)
    depth[0, 2:6, 2:6] = 1.0
    distance_map(model_edges(depth, depth), 4.0)
    recent_events(torch.zeros(8, 8, dtype=torch.int64), 1, 1, min_support=1)


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


if __name__ == "__main__":
    _worker()
