"""Benchmark suites: the standard 8 sequences and the wide suite's dev and test splits, generated in parallel.

A suite is a list of entries, plain dicts, one per sequence (:func:`wide_suite`, :func:`standard_suite`)::

    name, object, size, motion, camera, noise_rate, hot_pixels, hot_pixel_rate, refractory_us, occluder,
    texture, seed, duration, depth_range, contrast_threshold, sigma_c, background, render_backend, render_faces,
    max_px_per_frame

:func:`generate_suite` writes ``DIR/suite.json`` (the suite, its name, split and seed base) and one sequence
directory per entry (``DIR/<name>``), one process per core and one sequence per task
(:func:`generate_entry`, a plain top-level function of ``(entry, out_dir)`` that any executor can call).

The wide suite (``wide_suite(split)``) is a deterministic function of the split's seed base: 32 sequences of
4 s over 12 YCB objects (4 small, 4 medium, 4 large, by bounding-box diagonal), each factor balanced and
shuffled independently: the four motion groups (8 each), the three cameras (``davis346``, ``vga``, ``hd``),
background noise 0, 0.1, 0.5, 1 or 2 Hz per pixel, 0, 5 or 20 hot pixels at 100 Hz, a refractory period drawn
in 0-100 us, a hand in 8 of the 32 and a printed texture in 16, object distance 0.3-1.0 m; rendered with the
compiled raster backend, a frame per pixel of image motion. The dev and test
splits use disjoint seeds (``SPLIT_SEED_BASE``); the test split is for reporting only, never for choosing a
parameter. ``wide_suite(split, objects=object_sizes([...]))`` draws the same sequences over other objects.

Example:
    >>> entries = wide_suite("dev")
    >>> len(entries), len({e["object"] for e in entries}), sorted({e["motion"] for e in entries})
    (32, 12, ['fast', 'mixed', 'regular', 'turn'])
"""

from __future__ import annotations

import json
import os
import shutil
import time
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchevtrack.camera import Camera

__all__ = ["BENCHMARK_MOTIONS", "BENCHMARK_OBJECTS", "CAMERA_PRESETS", "MOTIONS", "SPLIT_SEED_BASE", "SUITES",
           "WIDE_OBJECTS", "benchmark_seed", "generate_entry", "generate_suite", "object_label", "object_sizes",
           "read_suite_json", "size_class", "standard_suite", "wide_suite", "write_suite_json"]

# The paper's synthetic benchmark: 4 YCB objects x 2 motion groups, named like the paper's tables.
BENCHMARK_OBJECTS = {
    "cracker": "003_cracker_box",
    "mustard": "006_mustard_bottle",
    "potted": "010_potted_meat_can",
    "tomato": "005_tomato_soup_can",
}
BENCHMARK_MOTIONS = ("regular", "fast")
MOTIONS = ("regular", "fast", "turn", "mixed")
CAMERA_PRESETS = {
    "davis346": Camera(346, 260, 255.0, 255.0, 173.0, 130.0),
    "vga": Camera.default(),
    "hd": Camera(1280, 720, 1000.0, 1000.0, 640.0, 360.0),
}
"""Sensor presets of ``--camera``: DAVIS346, a 640x480 sensor (Prophesee Gen3, the default camera), 1280x720
(Prophesee IMX636, the seed paper's real camera); principal point at the image centre."""


def benchmark_seed(short: str, motion: str) -> int:
    """Fixed seed of a benchmark sequence (stable across releases)."""
    return 1000 + 10 * list(BENCHMARK_OBJECTS).index(short) + BENCHMARK_MOTIONS.index(motion)


SUITES = ("standard", "wide")
SPLIT_SEED_BASE = {"dev": 200_000, "test": 300_000}
"""Seed of a split's first sequence; sequence ``i`` uses ``base + i`` (the splits' seed ranges never meet)."""

WIDE_OBJECTS = {
    "009_gelatin_box": "small", "007_tuna_fish_can": "small", "005_tomato_soup_can": "small",
    "010_potted_meat_can": "small",
    "025_mug": "medium", "008_pudding_box": "medium", "004_sugar_box": "medium", "006_mustard_bottle": "medium",
    "003_cracker_box": "large", "021_bleach_cleanser": "large", "035_power_drill": "large",
    "022_windex_bottle": "large",
}
"""The wide suite's objects and their :func:`size_class`."""


def size_class(extents) -> str:
    """``"small"``, ``"medium"`` or ``"large"``: bounding-box diagonal below 0.16 m, below 0.24 m, or larger.
    ``extents``: the box's three side lengths, metres."""
    diag = float(np.linalg.norm(np.asarray(extents, dtype=np.float64)))
    return "small" if diag < 0.16 else "medium" if diag < 0.24 else "large"

_WIDE_SIZE = 32
_WIDE_DURATION_S = 4.0
_CAMERAS = ("davis346", "vga", "hd")
_NOISE_HZ = (0.0, 0.1, 0.5, 1.0, 2.0)
_HOT_PIXELS = (0, 5, 20)
_HOT_PIXEL_RATE_HZ = 100.0
_WIDE_DEPTH_M = (0.3, 1.0)
_WIDE_BACKEND = "raster"
# A frame per pixel of image motion (the standard benchmark: half a pixel) halves the frames of the suite's fast
# sequences (e.g. 13211 -> 6005 for a 4 s mixed one); at 1000 px/s frames stay 1 ms apart, under the
# tracker's 2 ms update period.
_WIDE_MAX_PX = 1.0


def _balanced(rng: np.random.Generator, values, n: int, counts: dict | None = None) -> list:
    """``n`` values, each of ``values`` equally often (or ``counts`` times), in a random order."""
    if counts is None:
        pool = [values[i % len(values)] for i in range(n)]
    else:
        pool = [v for v, c in counts.items() for _ in range(c)]
    return [pool[i] for i in rng.permutation(n)]


def object_label(obj: str) -> str:
    """An object as tables show it: a name as it is, a mesh file (a path with a suffix) by its stem
    (``"scans/my_part.ply"`` -> ``"my_part"``)."""
    return Path(obj).stem if Path(obj).suffix else obj


def _short_name(obj: str) -> str:
    """A sequence name's object part: the suite's own objects by their first word (``"006_mustard_bottle"`` ->
    ``"mustard"``), any other by its :func:`object_label` without the YCB number, underscores made dashes so that
    the name's fields stay ``_``-separated (``"040_large_marker"`` -> ``"large-marker"``, ``"scans/my_part.ply"``
    -> ``"my-part"``)."""
    if obj in WIDE_OBJECTS:
        return obj.split("_", 1)[1].split("_")[0]
    stem = object_label(obj)
    if stem[:3].isdigit() and stem[3:4] == "_":
        stem = stem[4:]
    return stem.replace("_", "-")


def object_sizes(objects) -> dict[str, str]:
    """``{object: size class}`` of object names or mesh files (:func:`size_class` of each mesh's bounding box),
    in the order given, a mesh file by its absolute path (any worker finds it); the wide suite's own objects without
    loading them. Raises ``ValueError`` on an empty list or a repeated object (a balanced suite draws each equally
    often), and what :func:`torchevtrack.mesh.load_mesh` raises on an unknown name or an unreadable file."""
    from torchevtrack.mesh import load_mesh

    objects = [str(Path(o).resolve()) if Path(o).suffix and Path(o).is_file() else str(o) for o in objects]
    if not objects:
        raise ValueError("objects: give at least one object name or mesh file")
    if len(set(objects)) != len(objects):
        raise ValueError(f"objects: each object once, got {objects}")
    return {o: WIDE_OBJECTS.get(o) or size_class(load_mesh(o).extents) for o in objects}


def wide_suite(split: str, seed_base: int | None = None, objects: dict[str, str] | None = None) -> list[dict]:
    """The wide suite's entries of ``split`` (``"dev"`` or ``"test"``), a pure function of the seed base
    (default ``SPLIT_SEED_BASE[split]``) and the objects. See the module docstring for the design.

    ``objects``: ``{name or mesh file: size class}`` (:func:`object_sizes`) to draw instead of the suite's 12 YCB
    objects (``WIDE_OBJECTS``), each as often as the 32 sequences allow. Every other factor of sequence ``i``
    (motion, camera, noise, hand, texture, seed) is the same as in the default suite of that seed base, so the
    two are paired sequence by sequence.

    Example:
        >>> a = wide_suite("dev")
        >>> b = wide_suite("dev", objects={"box": "small", "can": "small"})
        >>> sorted({e["object"] for e in b}), [e["motion"] for e in a] == [e["motion"] for e in b]
        (['box', 'can'], True)
    """
    if split not in SPLIT_SEED_BASE:
        raise ValueError(f"split must be one of {sorted(SPLIT_SEED_BASE)}, got {split!r}")
    sizes = WIDE_OBJECTS if objects is None else dict(objects)
    if not 1 <= len(sizes) <= _WIDE_SIZE:
        raise ValueError(f"objects: give 1 to {_WIDE_SIZE} objects (one per sequence at most), got {len(sizes)}")
    base = SPLIT_SEED_BASE[split] if seed_base is None else int(seed_base)
    rng = np.random.default_rng(base)
    n = _WIDE_SIZE
    objects = _balanced(rng, list(sizes), n)
    motions = _balanced(rng, MOTIONS, n)
    cameras = _balanced(rng, _CAMERAS, n)
    noise = _balanced(rng, _NOISE_HZ, n)
    hot = _balanced(rng, _HOT_PIXELS, n)
    hand = _balanced(rng, None, n, {"hand": n // 4, "none": n - n // 4})
    texture = _balanced(rng, None, n, {"random": n // 2, "none": n - n // 2})
    refractory = rng.integers(0, 101, n)
    entries = []
    for i in range(n):
        entries.append({
            "name": f"{i:02d}_{_short_name(objects[i])}_{motions[i]}_{cameras[i]}",
            "object": objects[i],
            "size": sizes[objects[i]],
            "motion": motions[i],
            "camera": cameras[i],
            "noise_rate": float(noise[i]),
            "hot_pixels": int(hot[i]),
            "hot_pixel_rate": _HOT_PIXEL_RATE_HZ,
            "refractory_us": int(refractory[i]),
            "occluder": hand[i],
            "texture": texture[i],
            "seed": base + i,
            "duration": _WIDE_DURATION_S,
            "depth_range": list(_WIDE_DEPTH_M),
            "contrast_threshold": 0.2,
            "sigma_c": 0.03,
            "background": 0.2,
            "render_backend": _WIDE_BACKEND,
            "render_faces": None,
            "max_px_per_frame": _WIDE_MAX_PX,
        })
    return entries


def standard_suite(duration: float = 4.0, *, contrast_threshold: float = 0.2, sigma_c: float = 0.03,
                   refractory_us: int = 0, noise_rate: float = 0.0, background: float = 0.2,
                   render_faces: int | None = None) -> list[dict]:
    """The standard benchmark's 8 entries (4 objects x regular / fast, fixed seeds, 640x480, pyrender), with
    the simulator parameters given."""
    entries = []
    for short, name in BENCHMARK_OBJECTS.items():
        for motion in BENCHMARK_MOTIONS:
            entries.append({
                "name": f"{short}_{motion}", "object": name, "size": None, "motion": motion, "camera": "vga",
                "noise_rate": float(noise_rate), "hot_pixels": 0, "hot_pixel_rate": _HOT_PIXEL_RATE_HZ,
                "refractory_us": int(refractory_us), "occluder": "none", "texture": "none",
                "seed": benchmark_seed(short, motion), "duration": float(duration), "depth_range": [0.3, 0.7],
                "contrast_threshold": float(contrast_threshold), "sigma_c": float(sigma_c),
                "background": float(background), "render_backend": "pyrender", "render_faces": render_faces,
                "max_px_per_frame": 0.5,
            })
    return entries


def generate_entry(entry: dict, out_dir: str | Path, progress: bool = False) -> dict:
    """Generate one suite entry into ``out_dir/<name>`` and return ``{"name", "events", "seconds", "frames"}``.

    The sequence is written into a temporary sibling directory and renamed when complete, so an interrupted
    run leaves no half-written sequence. A plain top-level function of picklable arguments: any process pool
    or cluster executor can run it.
    """
    from torchevtrack.synth.generate import generate_sequence

    out = Path(out_dir) / entry["name"]
    start = time.perf_counter()
    seq = generate_sequence(
        entry["object"], entry["motion"], entry["duration"], entry["seed"], CAMERA_PRESETS[entry["camera"]],
        C=entry["contrast_threshold"], sigma_C=entry["sigma_c"], refractory_us=entry["refractory_us"],
        noise_rate_hz=entry["noise_rate"], hot_pixels=entry["hot_pixels"], hot_pixel_rate_hz=entry["hot_pixel_rate"],
        occluder=entry["occluder"], texture=entry["texture"], depth_range=tuple(entry["depth_range"]),
        background=entry["background"], render_faces=entry["render_faces"],
        render_backend=entry["render_backend"], max_px_per_frame=entry["max_px_per_frame"], progress=progress,
    )
    tmp = out.with_name(f".{out.name}.partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    seq.save(tmp)
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return {"name": entry["name"], "events": len(seq.events), "frames": seq.meta["generator"]["n_frames"],
            "seconds": time.perf_counter() - start}


def write_suite_json(out_dir: str | Path, suite: str, split: str | None, seed_base: int | None,
                     entries: list[dict]) -> Path:
    """Write ``out_dir/suite.json`` (via a temporary file in the same directory); returns its path."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    path = d / "suite.json"
    tmp = d / ".suite.json.tmp"
    tmp.write_text(json.dumps({"suite": suite, "split": split, "seed_base": seed_base, "sequences": entries},
                              indent=2) + "\n")
    tmp.replace(path)
    return path


def read_suite_json(bench_dir: str | Path) -> dict | None:
    """``bench_dir/suite.json`` as written by :func:`write_suite_json`, or ``None`` when there is none."""
    path = Path(bench_dir) / "suite.json"
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    if not isinstance(data, dict) or not isinstance(data.get("sequences"), list):
        raise ValueError(f"{path}: expected an object with a 'sequences' list")
    return data


def _cost(entry: dict) -> float:
    """A rough relative generation cost, to start the longest tasks first."""
    speed = {"regular": 1.0, "turn": 2.0, "fast": 4.0, "mixed": 5.0}.get(entry["motion"], 1.0)
    scale = {"davis346": 0.5, "vga": 1.0, "hd": 2.0}.get(entry["camera"], 1.0)
    return entry["duration"] * speed * scale * (1.5 if entry["occluder"] != "none" else 1.0)


def generate_suite(entries: list[dict], out_dir: str | Path, *, executor=None, jobs: int | None = None,
                   progress: bool = True) -> list[dict]:
    """Generate ``entries`` into ``out_dir``, longest first, one sequence per task of ``executor``
    (:mod:`torchevtrack.executor`; on a Ray cluster ``out_dir`` must be a path every node writes to), by default
    a local pool of ``jobs`` processes (default: the usable cores; one sequence or ``jobs=1``: in this process).
    Prints each sequence as it completes. Returns the per-sequence results of :func:`generate_entry` in entry
    order. A failing sequence stops the run (the others already written stay)."""
    from torchevtrack.executor import ProcessExecutor, SerialExecutor

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    order = sorted(entries, key=_cost, reverse=True)
    own = None
    if executor is None:
        workers = min(jobs or os.cpu_count() or 1, len(entries))
        executor = own = SerialExecutor() if workers <= 1 else ProcessExecutor(workers)

    def done(i: int, r: dict) -> None:
        tqdm.write(f"{out / r['name']}: {r['events']} events, {r['frames']} frames, {r['seconds']:.1f} s")

    try:
        finished = executor.map(partial(generate_entry, out_dir=out), order, desc="sequences", progress=progress,
                                on_done=done)
    finally:
        if own is not None:
            own.close()
    results = {r["name"]: r for r in finished}
    return [results[e["name"]] for e in entries]
