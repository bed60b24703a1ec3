"""The benchmark runner: the paper's ablations on a directory of sequences, batched, with a Table-I report.

:func:`run_benchmark` tracks every selected sequence of a benchmark directory (one sub-directory per
sequence, see the README's "Sequence directory format") with each method of
:data:`torchevtrack.config.ABLATIONS`. All sequences that share a camera run as **one batch** (one
:class:`~torchevtrack.tracker.EventPoseTracker` with one mesh and one event stream per sequence, each
starting at its own first ground-truth pose and time). It writes into ``out_dir``::

    results.json              per method and sequence: metrics (metrics.evaluate), loss detection and
                              timing; the config, torchevtrack / torch versions, machine and date
    table.md                  Table I of the paper (e_p(sigma) cm / e_r(sigma) deg), ADD-S AUC, tracking
                              loss, speed
    poses/<method>/<seq>.txt  tracked poses, TUM (the file that was scored); with trials, the first trial's,
                              and poses/<method>/trial<k>/<seq>.txt the others'
    plots/<seq>.png           translation / rotation error against time, all methods on the same axes
    overlays/<seq>_<k>.png    tracked (green) and ground-truth (magenta) contours over EROS, 3 instants
    overlays/<seq>.gif        the same over the first second, 50 ms steps

Metrics are those of :func:`torchevtrack.metrics.evaluate`: RMSE and population sigma of the
translation (cm) and rotation (deg) errors, ADD and ADD-S AUC on 0..10 cm (model points:
:func:`torchevtrack.metrics.mesh_points`, the same as ``torchevtrack eval``), and the EDOPT failure rule.

Start-pose robustness: with ``init_noise=(mm, deg)`` every sequence starts from its first ground-truth pose
moved by exactly ``mm`` millimetres along a random direction and turned by exactly ``deg`` degrees about a random
axis (:func:`torchevtrack.geometry.perturb_pose`), and ``trials`` such draws run per method (the same start poses
for every method). The tracker is deterministic but chaotic where it nearly fails: a start pose 10 um off can
change a sequence's error by centimetres, so one run is one draw. ``results[method][sequence]`` and the files
hold the first trial; ``trials[method][sequence]`` the metrics of every trial, and ``table.md`` their spread.

Tracking loss: every run carries the tracker's :class:`~torchevtrack.loss.LossDetector` (the config's
``loss`` parameters, switched on whatever ``loss.enabled`` says; alone it only reports, no pose changes). Per
sequence, :func:`torchevtrack.loss.compare_with_ground_truth` sets when loss was first declared against
the start of the first ground-truth failure run (the held runs' rule: a symmetric untextured object's spin about its
axis is no failure), whether a declaration still held detects that failure, and counts the declarations, the false
alarms (declared and found again before the first failure run) and the recoveries (the lost flag turning off):
``results[method][sequence]["loss"]`` (the first draw; each draw's in ``trials``, and the loss table's counts pool
them). The flags go beside each pose file (``poses/METHOD/S.lost.txt``, :mod:`torchevtrack.io.lost`); another
tracker's poses with such a side file get a loss-table row too. With ``recover.enabled`` (``benchmark --recover``)
the lost sequences are re-localised (:mod:`torchevtrack.recover`); the lost flags are then the recoverer's and each
run's timing counts its searches (``searches``, ``search_s``, ``restarts``).

Example:
    >>> from torchevtrack.benchmark import run_benchmark, table_markdown
    >>> res = run_benchmark("data/bench", "results", methods=("full",), only=["mustard_regular"],
    ...                     duration_s=0.5)                              # doctest: +SKIP
    >>> print(table_markdown(res))                                       # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import platform
import time
from collections.abc import Iterable, Sequence as SequenceABC
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

import torchevtrack
from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.executor import Executor, SerialExecutor
from torchevtrack.geometry import perturb_pose
from torchevtrack.io.atomic import write_text
from torchevtrack.io.lost import lost_beside, lost_path, write_lost
from torchevtrack.io.poses import read_poses, read_tum, write_tum
from torchevtrack.loss import LOSS_DELAY_US, compare_with_ground_truth

from torchevtrack.mesh import hidden_symmetry_axis
from torchevtrack.metrics import (FAIL_R_DEG, FAIL_T_M, FAIL_WINDOW, evaluate, mesh_points, per_pose_errors,
                                  sym_failed, sym_rmse_r_deg)
from torchevtrack.synth.sequence import SEQUENCE_FILES, TEXTURED_MESH, Sequence
from torchevtrack.tracker import EventPoseTracker

__all__ = [
    "METHODS",
    "METHOD_NAMES",
    "find_sequences",
    "run_benchmark",
    "table_markdown",
]

METHODS = ("no_ukf", "full", "velocity_only", "correction_only", "edopt_vel")
"""The default methods: the paper's ablations (:data:`torchevtrack.config.ABLATIONS` but ``hypotheses``, which takes
about 2.3x the time of ``full``), the default config (``no_ukf``) first."""

METHOD_NAMES = {
    "correction_only": "EDOPT (correction only)",
    "edopt_vel": "EDOPT_Vel",
    "velocity_only": "Ours (only Vel)",
    "no_ukf": "Ours (w/o ukf; the default config)",
    "full": "Ours (ukf)",
    "hypotheses": "Ours (ukf, and w/o ukf: the better)",
}
"""Row names of the table, in the paper's row order (then the method with two hypotheses)."""

_OBJECT_ORDER = ("mustard", "potted", "cracker", "tomato")  # the paper's column order within a group
_GROUP_ORDER = ("regular", "fast")
_GIF_SPAN_US = 1_000_000
_GIF_STEP_US = 50_000
_GIF_FPS = 10.0  # 50 ms steps shown at half speed
_OVERLAY_INSTANTS = 3


# -- inputs ---------------------------------------------------------------------------------------
def find_sequences(bench_dir: str | Path, only: Iterable[str] | None = None) -> list[Path]:
    """Sequence directories of ``bench_dir`` (sub-directories holding all sequence files), sorted by name.

    ``only``: keep these names (each must exist). Raises ``FileNotFoundError`` / ``ValueError``.
    """
    root = Path(bench_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"benchmark directory not found: {root}")
    found = {d.name: d for d in sorted(root.iterdir())
             if d.is_dir() and all((d / f).is_file() for f in SEQUENCE_FILES)}
    if only is not None:
        only = list(only)
        missing = [n for n in only if n not in found]
        if missing:
            raise ValueError(f"only: no sequence named {missing} in {root}; found {sorted(found)}")
        found = {n: found[n] for n in sorted(set(only))}
    if not found:
        raise ValueError(f"{root} holds no sequence directory (each needs {', '.join(SEQUENCE_FILES)})")
    return list(found.values())


@dataclass
class _Item:
    """One sequence prepared for tracking."""

    name: str
    path: Path
    seq: Sequence
    group: str
    t_start_us: int
    t_end_us: int
    n_updates: int
    points: torch.Tensor
    symmetry_axis: torch.Tensor | None  # continuous symmetry of an untextured mesh (its rotation is unobservable)


def _group(name: str, meta: dict) -> str:
    motion = meta.get("motion")
    if isinstance(motion, str) and motion:
        return motion
    suffix = name.rsplit("_", 1)[-1]
    return suffix if suffix in _GROUP_ORDER else "other"


def _prepare(path: Path, duration_s: float | None, period_us: int) -> _Item:
    seq = Sequence.load(path)
    t0 = int(seq.gt_t_us[0])
    t1 = int(seq.gt_t_us[-1])
    if duration_s is not None:
        t1 = min(t1, t0 + round(duration_s * 1e6))
    n = (t1 - t0) // period_us
    if n < 1:
        raise ValueError(f"sequence {path.name}: {(t1 - t0) / 1e6:.4f} s to track is shorter than one update "
                         f"period ({period_us} us)")
    seq.events = seq.events.slice_time(seq.events.t_start, t1 + 1)
    axis = hidden_symmetry_axis(seq.mesh)
    return _Item(path.name, path, seq, _group(path.name, seq.meta), t0, t1, n, mesh_points(seq.mesh.vertices),
                 None if axis is None else torch.as_tensor(axis))


# -- running --------------------------------------------------------------------------------------
def _check_methods(methods) -> list[str]:
    if isinstance(methods, str):
        methods = [methods]
    methods = list(dict.fromkeys(methods))
    unknown = [m for m in methods if m not in ABLATIONS]
    if unknown or not methods:
        raise ValueError(f"methods must be a non-empty subset of {sorted(ABLATIONS)}, got {methods}")
    return methods


def _start_poses(items: list[_Item], init_noise: tuple[float, float] | None, trials: int,
                 seed: int) -> list[dict[str, torch.Tensor]]:
    """Per trial, each item's start pose: its first ground-truth pose, perturbed by ``init_noise`` (mm, deg)
    with the generator seeded ``seed + trial`` (items in order)."""
    starts = []
    for k in range(trials):
        g = torch.Generator().manual_seed(seed + k)
        starts.append({it.name: it.seq.gt_poses[0] if init_noise is None else
                       perturb_pose(it.seq.gt_poses[0], init_noise[0] / 1e3, math.radians(init_noise[1]), g)
                       for it in items})
    return starts


def _check_trials(init_noise, trials, seed) -> tuple[float, float] | None:
    if init_noise is not None:
        mm, deg = (float(v) for v in init_noise)
        if not (math.isfinite(mm) and math.isfinite(deg) and mm >= 0 and deg >= 0):
            raise ValueError(f"init_noise must be (mm, deg), finite and >= 0, got {init_noise!r}")
        init_noise = (mm, deg)
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ValueError(f"trials must be an integer >= 1, got {trials!r}")
    if trials > 1 and init_noise is None:
        raise ValueError("trials > 1 needs init_noise: without it every trial tracks the same start poses")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    return init_noise


def _trial_metrics(m: dict) -> dict:
    keys = ("rmse_t_cm", "rmse_r_deg", "adds_auc", "failed", "rmse_r_sym_deg", "failed_sym")
    return {k: m[k] for k in keys if k in m}


def _track(items: list[_Item], camera: Camera, cfg: TrackerConfig, progress: bool, starts: dict[str, torch.Tensor],
           textured: bool = False):
    """Track ``items`` as one batch from their ``starts``; per item its own ``(t_us (n_i,), poses (n_i, 7),
    lost (n_i,))`` and the timing (the loss detector runs, passively, whatever the config says). ``textured``: each
    item's :data:`~torchevtrack.synth.sequence.TEXTURED_MESH` where it has one is the tracker's mesh."""
    setup = time.perf_counter()
    tracker = EventPoseTracker(camera, [str(_mesh_file(it.path, textured)) for it in items],
                               cfg.replace(loss={"enabled": True}))
    start = time.perf_counter()
    try:
        times, poses, lost = tracker.track([it.seq.events for it in items],
                                           torch.stack([starts[it.name] for it in items]),
                                           t_start_us=[it.t_start_us for it in items],
                                           t_end_us=[it.t_end_us for it in items], progress=progress,
                                           return_lost=True)
    finally:
        tracker.close()
    wall = time.perf_counter() - start
    steps = times.shape[1]
    run = {
        "sequences": [it.name for it in items],
        "batch_size": len(items),
        "updates": steps,
        "setup_s": start - setup,
        "wall_s": wall,
        "updates_per_s": steps / wall,
        "sequence_updates_per_s": sum(it.n_updates for it in items) / wall,
        "tracked_s": sum(it.n_updates for it in items) * cfg.period_us / 1e6,
    }
    run["realtime_factor"] = run["tracked_s"] / wall
    if tracker.recover is not None:  # recover.enabled: the searches' share of the wall time
        run.update(searches=tracker.recover.searches, search_s=tracker.recover.search_s,
                   restarts=tracker.recover.restarts)
    out = [(times[i, :it.n_updates].clone(), poses[i, :it.n_updates].clone(), lost[i, :it.n_updates].clone())
           for i, it in enumerate(items)]
    return out, run


def _mesh_file(path: Path, textured: bool) -> Path:
    """The mesh a sequence directory gives the tracker: its printed model if asked for and there, else ``mesh.ply``."""
    return path / TEXTURED_MESH if textured and (path / TEXTURED_MESH).is_file() else path / "mesh.ply"


def _check_predictions(predictions, methods: list[str]) -> dict[str, Path]:
    if predictions is None:
        return {}
    out = {}
    for name, directory in dict(predictions).items():
        if not isinstance(name, str) or not name or name in methods or name in ABLATIONS:
            raise ValueError(f"prediction name {name!r} must be a non-empty name other than the package's methods "
                             f"{sorted(ABLATIONS)}")
        if not Path(directory).is_dir():
            raise FileNotFoundError(f"predictions of {name!r}: directory not found: {directory}")
        out[name] = Path(directory)
    return out


def _pose_file(directory: Path, name: str) -> Path:
    """The one pose file of sequence ``name`` in ``directory``: ``name.txt``, ``name.csv`` or ``name.json``."""
    found = [directory / f"{name}{ext}" for ext in (".txt", ".csv", ".json") if (directory / f"{name}{ext}").is_file()]
    if len(found) != 1:
        raise FileNotFoundError(f"{directory}: expected one pose file {name}.txt (or .csv, .json) for sequence "
                                f"{name}, found {[p.name for p in found] or 'none'}")
    return found[0]


def _score_foreign(it: _Item, path: Path, crop: bool) -> tuple[dict, dict, dict | None]:
    """Score another tracker's poses of ``it`` in ``path`` as ``torchevtrack eval`` does (``crop``: without the
    poses after ``it.t_end_us``); returns the :func:`evaluate` dict, the :func:`per_pose_errors` for the plots and,
    where ``path`` has a lost-flag side file (:mod:`torchevtrack.io.lost`), the
    :func:`~torchevtrack.loss.compare_with_ground_truth` dict (else None)."""
    t_us, poses = read_poses(path)
    lost = lost_beside(path, t_us)
    if crop and t_us.numel() and int(t_us[-1]) > it.t_end_us:
        keep = t_us <= it.t_end_us
        t_us, poses = t_us[keep], poses[keep]
        lost = None if lost is None else lost[keep]
    gt_t, gt = it.seq.gt_t_us, it.seq.gt_poses
    try:
        metrics = evaluate(t_us, poses, gt_t, gt, mesh_points=it.points, symmetry_axis=it.symmetry_axis)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    loss = None if lost is None else compare_with_ground_truth(t_us, lost, poses, gt_t, gt,
                                                               symmetry_axis=it.symmetry_axis)
    return metrics, per_pose_errors(t_us, poses, gt_t, gt), loss


@dataclass
class _TrackTask:
    """One tracking run of the benchmark: ``method``'s config on a batch of sequences, from the start poses of
    draw ``trial``. Sent to an executor's workers without ``items``: they load the sequences from ``paths``."""

    method: str
    trial: int
    paths: list[Path]
    duration_s: float | None
    config: TrackerConfig
    starts: dict[str, torch.Tensor]
    progress: bool
    textured: bool = False
    items: list[_Item] | None = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "items": None}


def _run_task(task: _TrackTask):
    """:func:`_track` of a task (in any process): per sequence ``(t_us, poses, lost)`` and the run's timing."""
    items = task.items or [_prepare(p, task.duration_s, task.config.period_us) for p in task.paths]
    return _track(items, items[0].seq.camera, task.config, task.progress, task.starts, task.textured)


def _machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch_version": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
    }


def run_benchmark(
    bench_dir: str | Path,
    out_dir: str | Path,
    *,
    methods: SequenceABC[str] = METHODS,
    only: Iterable[str] | None = None,
    duration_s: float | None = None,
    config: TrackerConfig | str | Path | None = None,
    batch: bool = True,
    overlays: bool = True,
    progress: bool = True,
    init_noise: tuple[float, float] | None = None,
    trials: int = 1,
    seed: int = 0,
    predictions: dict[str, str | Path] | None = None,
    executor: Executor | None = None,
    textured: bool = False,
) -> dict:
    """Run the ablation benchmark and write its report (see the module docstring for the files).

    Args:
        bench_dir: directory of sequence directories.
        out_dir: output directory (created).
        methods: names in :data:`torchevtrack.config.ABLATIONS`.
        only: sequence names to run (default: all).
        duration_s: track only the first seconds of each sequence (default: its whole ground truth).
        config: base :class:`TrackerConfig` or a YAML path; each method applies its ablation on top.
        batch: one batch per method and camera (default) or one run per sequence. Results agree to
            float32 rounding; only the timing differs. A parallel ``executor`` runs one sequence per task (no
            batches), so that the sequences spread over its workers.
        overlays: write the overlay PNGs and GIFs (for ``"no_ukf"``, the default config, else the first method).
        progress: tqdm bars over methods and updates.
        init_noise: ``(mm, deg)``: start every sequence from its first ground-truth pose moved and turned by
            exactly this much in random directions (module docstring); ``None``: from that pose.
        trials: draws of the start poses per method (``> 1`` needs ``init_noise``); seed: the first draw's
            generator seed (trial ``k`` uses ``seed + k``).
        predictions: other trackers' poses, ``{name: directory}``: method ``name`` reads sequence ``S`` from
            ``directory/S.txt`` (or ``S.csv``, ``S.json``: any format of :func:`torchevtrack.io.poses.read_poses`)
            and is scored as ``torchevtrack eval`` scores that file (with ``duration_s``, its poses after the
            tracked span are left out), in every table and plot.
        executor: where the tracking runs go (:mod:`torchevtrack.executor`; default serial in this process):
            each (batch of sequences, method, draw) is one task, read from disk by the worker (on a cluster the
            benchmark directory must be at the same path on every node). The results do not depend on it.
        textured: track each sequence that has its printed model (:data:`~torchevtrack.synth.sequence.TEXTURED_MESH`,
            written by ``synth --texture random``) with that model instead of ``mesh.ply``, as a user with a
            textured scan of the object would; the scoring is the same (the geometry is).

    Returns:
        The dict written to ``results.json``: ``results[method][sequence]`` holds ``metrics`` (the
        :func:`~torchevtrack.metrics.evaluate` dict), ``loss`` (the
        :func:`~torchevtrack.loss.compare_with_ground_truth` dict), ``timing`` and ``pose_file``; ``runs[method]``
        the batched runs; ``sequences``, ``config``, ``machine``, ``executor`` (its name), versions, date. With
        ``init_noise``, also ``init_noise`` (with each trial's ``start_poses``) and ``trials[method][sequence]``: per
        trial the RMSEs, ADD-S AUC and failure flags. With ``predictions``, ``results[name][sequence]`` holds
        ``metrics`` and ``pose_file`` (no loss, no timing) and ``predictions`` their directories.
    """
    methods = _check_methods(methods)
    predictions = _check_predictions(predictions, methods)
    if executor is not None and not isinstance(executor, Executor):
        raise TypeError(f"executor must be a torchevtrack.executor.Executor or None, got {type(executor).__name__}")
    init_noise = _check_trials(init_noise, trials, seed)
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"duration_s must be positive seconds or None, got {duration_s!r}")
    if isinstance(config, (str, Path)):
        config = TrackerConfig.from_yaml(config)
    elif config is not None and not isinstance(config, TrackerConfig):
        raise TypeError(f"config must be a TrackerConfig, a YAML path or None, got {type(config).__name__}")
    base = config or TrackerConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    items = [_prepare(p, duration_s, base.period_us) for p in find_sequences(bench_dir, only)]
    foreign = {name: {it.name: _pose_file(d, it.name) for it in items} for name, d in predictions.items()}
    by_camera: dict[Camera, list[_Item]] = {}
    for it in items:
        by_camera.setdefault(it.seq.camera, []).append(it)
    ex = executor or SerialExecutor()
    batch = batch and not ex.parallel
    batches = list(by_camera.values()) if batch else [[it] for it in items]

    res: dict = {
        "torchevtrack_version": torchevtrack.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": _machine(),
        "bench_dir": str(Path(bench_dir).resolve()),
        "duration_s": duration_s,
        "batch": batch,
        "executor": ex.name,
        "textured": bool(textured),
        "methods": methods,
        "config": base.to_dict(),
        "ablations": {m: ABLATIONS[m] for m in methods},
        "sequences": {
            it.name: {"group": it.group, "object": it.seq.meta.get("object"), "t_start_us": it.t_start_us,
                      "t_end_us": it.t_end_us, "updates": it.n_updates, "events": len(it.seq.events),
                      "mesh_points": int(it.points.shape[0]), "camera": dataclasses.asdict(it.seq.camera),
                      "mesh": _mesh_file(it.path, textured).name,
                      "symmetry_axis": None if it.symmetry_axis is None else it.symmetry_axis.tolist()}
            for it in items
        },
        "runs": {},
        "results": {},
    }
    starts = _start_poses(items, init_noise, trials, seed)
    if init_noise is not None:
        res["init_noise"] = {"translation_mm": init_noise[0], "rotation_deg": init_noise[1], "trials": trials,
                             "seed": seed, "start_poses": [{k: v.tolist() for k, v in s.items()} for s in starts]}
        res["trials"] = {}
    curves: dict[str, dict[str, tuple]] = {it.name: {} for it in items}
    tracked: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    overlay_method = "no_ukf" if "no_ukf" in methods else methods[0]

    tasks = [_TrackTask(method, k, [it.path.resolve() for it in group], duration_s,
                        base.replace(**ABLATIONS[method]), {it.name: starts[k][it.name] for it in group},
                        progress and not ex.parallel, bool(textured), group)
             for method in methods for k in range(trials) for group in batches]
    outputs = ex.map(_run_task, tasks, desc="tracking runs", progress=progress)
    for method in methods:
        res["runs"][method], res["results"][method] = [], {}
    for task, (trajs, run) in zip(tasks, outputs):
        method, k, group, cfg = task.method, task.trial, task.items, task.config
        res["runs"][method].append(run)
        for it, (t_us, poses, lost) in zip(group, trajs):
            rel = Path("poses") / method / ("" if k == 0 else f"trial{k}") / f"{it.name}.txt"
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            write_tum(out / rel, t_us, poses)
            write_lost(lost_path(out / rel), t_us, lost)
            t_us, poses = read_tum(out / rel)  # score exactly what was written
            gt_t, gt = it.seq.gt_t_us, it.seq.gt_poses
            metrics = evaluate(t_us, poses, gt_t, gt, mesh_points=it.points, symmetry_axis=it.symmetry_axis)
            loss = compare_with_ground_truth(t_us, lost, poses, gt_t, gt, symmetry_axis=it.symmetry_axis)
            if init_noise is not None:
                res["trials"].setdefault(method, {}).setdefault(it.name, [None] * trials)[k] = \
                    {**_trial_metrics(metrics), "loss": loss}
            if k > 0:  # the first trial gives the tables, plots and overlays
                continue
            timing = {key: run[key] for key in ("batch_size", "wall_s", "updates_per_s")}
            timing["updates"] = int(t_us.numel())
            timing["realtime_factor"] = timing["updates"] * cfg.period_us / 1e6 / run["wall_s"]
            res["results"][method][it.name] = {"metrics": metrics, "loss": loss, "timing": timing,
                                               "pose_file": str(rel)}
            e = per_pose_errors(t_us, poses, gt_t, gt)
            curves[it.name][METHOD_NAMES[method]] = (
                ((e["t_us"] - it.t_start_us).double() / 1e6).numpy(),
                (e["te"] * 100.0).numpy(),
                torch.rad2deg(e["re"]).numpy(),
            )
            if method == overlay_method:
                tracked[it.name] = (t_us, poses)

    for name, files in foreign.items():
        res["results"][name] = {}
        for it in items:
            path = files[it.name]
            metrics, e, loss = _score_foreign(it, path, crop=duration_s is not None)
            res["results"][name][it.name] = {"metrics": metrics, "pose_file": str(path)}
            if loss is not None:
                res["results"][name][it.name]["loss"] = loss
            curves[it.name][name] = (((e["t_us"] - it.t_start_us).double() / 1e6).numpy(), (e["te"] * 100.0).numpy(),
                                     torch.rad2deg(e["re"]).numpy())
    if predictions:
        res["predictions"] = {name: str(Path(d).resolve()) for name, d in predictions.items()}

    from torchevtrack import viz

    for it in items:
        viz.plot_errors_multi(curves[it.name], out / "plots" / f"{it.name}.png", title=it.name)
    res["plots"] = {it.name: f"plots/{it.name}.png" for it in items}
    res["overlay_method"] = overlay_method if overlays else None
    res["overlays"] = {}
    if overlays:
        for it in tqdm(items, desc="overlays", unit="seq", disable=not progress):
            res["overlays"][it.name] = _write_overlays(it, tracked[it.name], base, out / "overlays")

    write_text(out / "results.json", json.dumps(res, indent=2) + "\n")
    write_text(out / "table.md", table_markdown(res))
    return res


def _write_overlays(it: _Item, pred: tuple[torch.Tensor, torch.Tensor], cfg: TrackerConfig, out: Path) -> list[str]:
    """PNGs at 3 update times (a third, two thirds and the end) and a GIF over the first second."""
    from torchevtrack import viz

    t_us = pred[0]
    n = t_us.numel()
    stills = [t_us[min(n - 1, max(0, (k + 1) * n // _OVERLAY_INSTANTS - 1))] for k in range(_OVERLAY_INSTANTS)]
    span = min(_GIF_SPAN_US, int(t_us[-1]) - it.t_start_us)
    step = max(min(_GIF_STEP_US, span // 5), cfg.period_us)
    gif = [it.t_start_us + step * k for k in range(1, span // step + 1)]
    times = torch.unique(torch.tensor([int(s) for s in stills] + gif, dtype=torch.int64))
    frames = dict(zip(times.tolist(), viz.iter_overlay_frames(
        it.seq.events, it.seq.camera, it.seq.mesh, pred, times, (it.seq.gt_t_us, it.seq.gt_poses),
        kernel_size=cfg.eros.kernel_size, decay=cfg.eros.decay)))
    out.mkdir(parents=True, exist_ok=True)
    written = []
    import imageio.v3 as iio

    for k, s in enumerate(stills):
        path = out / f"{it.name}_{k}.png"
        iio.imwrite(path, frames[int(s)])
        written.append(f"overlays/{path.name}")
    path = viz.save_video((frames[t] for t in gif), out / f"{it.name}.gif", fps=_GIF_FPS)
    written.append(f"overlays/{path.name}")
    return written


# -- report ---------------------------------------------------------------------------------------
def _column_order(sequences: dict) -> list[str]:
    def key(name: str):
        group = sequences.get(name, {}).get("group", "other")
        g = _GROUP_ORDER.index(group) if group in _GROUP_ORDER else len(_GROUP_ORDER)
        o = next((i for i, obj in enumerate(_OBJECT_ORDER) if name.startswith(obj)), len(_OBJECT_ORDER))
        return g, o, name

    return sorted(sequences, key=key)


def _row_order(methods: Iterable[str]) -> list[str]:
    order = list(METHOD_NAMES)
    return sorted(methods, key=lambda m: (order.index(m) if m in order else len(order), m))


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def table_markdown(results: dict) -> str:
    """The report of :func:`run_benchmark` as Markdown (``results`` as returned or read from ``results.json``).

    Table I of the paper: one row per method (paper row order and names), one column per sequence,
    regular before fast (mustard, potted, cracker, tomato), each cell ``e_p(sigma) / e_r(sigma)``:
    RMSE and population standard deviation of the translation error (cm) and the rotation error (deg),
    two decimals, a trailing ``†`` when the sequence failed. The Mean column averages the RMSE and the
    sigma over the sequences. Then ADD-S AUC (%), tracking loss (when the loss detector first declared
    the sequence lost against the start of its first failure run, in seconds from the sequence start;
    results without loss entries skip it) and the tracking speed.
    """
    try:
        per_method = results["results"]
        sequences = results["sequences"]
    except (TypeError, KeyError):
        raise ValueError("results must be the dict of run_benchmark (keys 'results' and 'sequences')") from None
    cols = _column_order(sequences)
    rows = _row_order(per_method)
    groups = [sequences[c].get("group", "other") for c in cols]
    lines = ["# Benchmark", ""]
    dur = results.get("duration_s")
    lines.append(f"torchevtrack {results.get('torchevtrack_version', '?')}, {results.get('date', '?')}; "
                 f"{'first ' + format(dur, 'g') + ' s of each sequence' if dur else 'whole sequences'}; "
                 f"columns: {', '.join(dict.fromkeys(groups))} sequences"
                 + ("; printed objects tracked with their textured models." if results.get("textured") else "."))
    lines += ["", "## Pose error: e_p(σ) cm / e_r(σ) deg", ""]
    lines.append(_row(["Method"] + cols + ["Mean"]))
    lines.append(_row(["---"] * (len(cols) + 2)))
    any_failed = False
    for m in rows:
        cells, means = [METHOD_NAMES.get(m, m)], []
        for c in cols:
            r = per_method[m].get(c)
            if r is None:
                cells.append("–")
                continue
            x = r["metrics"]
            vals = (x["rmse_t_cm"], x["std_t_cm"], x["rmse_r_deg"], x["std_r_deg"])
            means.append(vals)
            failed = bool(x["failed"])
            any_failed |= failed
            cells.append(_cell(vals) + ("†" if failed else ""))
        cells.append(_cell(tuple(np.mean(means, axis=0))) if means else "–")
        lines.append(_row(cells))
    lines.append("")
    lines.append("RMSE (σ: population standard deviation) of the translation error (cm) and the geodesic rotation "
                 "error (deg) over the updates; Mean: average over the sequences, failed ones included.")
    if any_failed:
        lines.append(f"† failed: translation error > {FAIL_T_M * 100:g} cm or rotation error > {FAIL_R_DEG:g} deg "
                     f"for {FAIL_WINDOW} consecutive updates (EDOPT rule).")

    sym = [c for c in cols if sequences[c].get("symmetry_axis") is not None]
    if sym and all("rmse_r_sym_deg" in per_method[m][c]["metrics"] for m in rows for c in sym if c in per_method[m]):
        lines += ["", "## Rotation error modulo the symmetry axis: e_r(σ) deg", ""]
        lines.append(_row(["Method"] + sym))
        lines.append(_row(["---"] * (len(sym) + 1)))
        for m in rows:
            cells = [METHOD_NAMES.get(m, m)]
            for c in sym:
                x = per_method[m].get(c, {}).get("metrics")
                cells.append("–" if x is None else f"{x['rmse_r_sym_deg']:.2f}({x['std_r_sym_deg']:.2f})"
                             + ("†" if x["failed_sym"] else ""))
            lines.append(_row(cells))
        lines.append("")
        lines.append("Objects whose untextured shape is symmetric about an axis (torchevtrack.mesh.symmetry_axis): "
                     "rotations about it change no edge, so no tracker observes them. Here the rotation error is "
                     "the angle between the estimated and the true axis, and † applies the EDOPT rule to it.")

    lines += ["", "## ADD-S AUC (%, 0–10 cm)", ""]
    lines.append(_row(["Method"] + cols + ["Mean"]))
    lines.append(_row(["---"] * (len(cols) + 2)))
    for m in rows:
        vals = [per_method[m][c]["metrics"]["adds_auc"] if c in per_method[m] else None for c in cols]
        have = [v for v in vals if v is not None]
        cells = [METHOD_NAMES.get(m, m)] + [f"{100 * v:.2f}" if v is not None else "–" for v in vals]
        cells.append(f"{100 * float(np.mean(have)):.2f}" if have else "–")
        lines.append(_row(cells))

    if results.get("trials"):
        lines += _trials_table(results, cols)

    loss_rows = [m for m in rows if all("loss" in r for r in per_method[m].values())]  # others: with side files
    if loss_rows:
        lines += ["", "## Tracking loss: declared / failed (s)", ""]
        lines.append(_row(["Method"] + cols + ["detected", "missed", "false alarms", "within 50 ms",
                                               "false alarms / min", "recoveries"]))
        lines.append(_row(["---"] * (len(cols) + 7)))
        for m in loss_rows:
            cells = [METHOD_NAMES.get(m, m)]
            for c in cols:
                r = per_method[m].get(c)
                t0 = sequences[c]["t_start_us"]
                cells.append("–" if r is None else " / ".join(
                    "–" if v is None else f"{(v - t0) / 1e6:.3f}"
                    for v in (r["loss"]["first_loss_us"], r["loss"]["first_failure_us"])))
            drawn = [x.get("loss") for runs in ((results.get("trials") or {}).get(m) or {}).values() for x in runs]
            losses = (drawn if drawn and all(x is not None for x in drawn)  # every draw where there are several
                      else [r["loss"] for r in per_method[m].values()])
            cells += [str(sum(x["first_failure_us"] is not None and not x["missed"] for x in losses)),
                      str(sum(x["missed"] for x in losses)), str(sum(x["false_alarm"] for x in losses))]
            failed = [x for x in losses if x["first_failure_us"] is not None]
            soon = sum(x["delay_us"] is not None and x["delay_us"] <= LOSS_DELAY_US for x in failed)
            minutes = sum(x.get("tracked_us", 0) for x in losses) / 60e6
            cells += [f"{soon} of {len(failed)}",
                      f"{sum(x.get('false_alarms', 0) for x in losses) / minutes:.2f}" if minutes > 0 else "–",
                      str(sum(x.get("recoveries", 0) for x in losses))]
            lines.append(_row(cells))
        lines.append("")
        lines.append("Per sequence the first draw; the counts pool every draw (with trials). "
                     "declared: first update the loss detector held the sequence lost; failed: first of "
                     f"{FAIL_WINDOW} consecutive updates with translation error > {FAIL_T_M * 100:g} cm or rotation "
                     f"error > {FAIL_R_DEG:g} deg (for a symmetric untextured object the tilt of its axis, as for the "
                     "held runs); –: never. detected: failed, and held lost when the failure run "
                     "began or declared lost after it; missed: failed, not detected; false alarms: declared, never "
                     f"failed; within 50 ms: failed sequences detected at most {LOSS_DELAY_US // 1000} ms after the "
                     "failure run began (or held lost since before); false alarms / min: declarations found again "
                     "before the first failure run began (all, in a sequence that never failed) per minute tracked; "
                     "recoveries: updates where the lost flag turned off (the re-localiser's restarts, with "
                     "recover.enabled).")

    runs = results.get("runs") or {}
    if runs:
        lines += ["", "## Speed", ""]
        lines.append(_row(["Method", "batch sizes", "updates/s", "sequence-updates/s", "real-time factor"]))
        lines.append(_row(["---"] * 5))
        for m in _row_order(runs):
            rs = runs[m]
            wall = sum(r["wall_s"] for r in rs)
            steps = sum(r["updates"] for r in rs)
            seq_updates = sum(r["sequence_updates_per_s"] * r["wall_s"] for r in rs)
            tracked = sum(r["tracked_s"] for r in rs)
            lines.append(_row([METHOD_NAMES.get(m, m), " + ".join(str(r["batch_size"]) for r in rs),
                               f"{steps / wall:.1f}", f"{seq_updates / wall:.1f}", f"{tracked / wall:.3f}"]))
        lines.append("")
        lines.append("updates/s: batched tracker steps per second (each step updates every sequence of the batch); "
                     "real-time factor: tracked seconds per wall-clock second.")
    return "\n".join(lines) + "\n"


def _trials_table(results: dict, cols: list[str]) -> list[str]:
    """The spread over the trials of perturbed start poses: per sequence the mean and standard deviation (over the
    trials) of e_p and the failed trials; then the means over the sequences, as mean and standard deviation over
    the trials, the median e_p over every run and the failed runs; where a run has ``failed_sym`` (a symmetry axis)
    also the mean e_r and the failed runs with the rotation about that axis left out (other runs count whole)."""
    noise, per_method = results["init_noise"], results["trials"]
    K = noise["trials"]
    sym = any("failed_sym" in x for runs in per_method.values() for seq in runs.values() for x in seq)
    lines = ["", f"## Start poses perturbed by {noise['translation_mm']:g} mm and {noise['rotation_deg']:g} deg: "
             f"{K} trials (seed {noise['seed']})", ""]
    summary = ["Mean e_p (cm)", "Median e_p (cm)", "Mean e_r (deg)", "ADD-S AUC (%)", "failed runs"]
    if sym:
        summary += ["Mean e_r, sym. (deg)", "failed runs, sym."]
    lines.append(_row(["Method"] + cols + summary))
    lines.append(_row(["---"] * (len(cols) + 1 + len(summary))))
    for m in _row_order(per_method):
        runs = per_method[m]
        cells = [METHOD_NAMES.get(m, m)]
        for c in cols:
            if c not in runs:
                cells.append("–")
                continue
            failed = sum(bool(x["failed"]) for x in runs[c])
            cells.append(_spread([x["rmse_t_cm"] for x in runs[c]]) + (f" ({failed}/{K}†)" if failed else ""))
        have = [runs[c] for c in cols if c in runs]
        means = {key: [np.mean([seq[k][key] for seq in have]) for k in range(K)]
                 for key in ("rmse_t_cm", "rmse_r_deg", "adds_auc")}
        n_runs = K * len(have)
        cells += [_spread(means["rmse_t_cm"]), f"{np.median([x['rmse_t_cm'] for seq in have for x in seq]):.2f}",
                  _spread(means["rmse_r_deg"]), _spread(means["adds_auc"], 100.0),
                  f"{sum(bool(x['failed']) for seq in have for x in seq)}/{n_runs}"]
        if sym:  # the symmetry axis left out where a sequence has one, the whole rotation error elsewhere
            r_sym = [np.mean([sym_rmse_r_deg(seq[k]) for seq in have]) for k in range(K)]
            cells += [_spread(r_sym), f"{sum(sym_failed(x) for seq in have for x in seq)}/{n_runs}"]
        lines.append(_row(cells))
    lines.append("")
    lines.append("Per sequence: e_p RMSE (cm), mean ± standard deviation over the trials, († failed trials, EDOPT "
                 "rule). Means: over the sequences per trial, then mean ± standard deviation over the trials; median: "
                 "over every run." + (" sym.: the rotation about the symmetry axis of a symmetric untextured object "
                                      "left out (see above), for the error and the EDOPT rule." if sym else ""))
    return lines


def _spread(values, scale: float = 1.0) -> str:
    return f"{np.mean(values) * scale:.2f} ± {np.std(values) * scale:.2f}"


def _cell(vals) -> str:
    tp, ts, rp, rs = (float(v) for v in vals)
    return f"{tp:.2f}({ts:.2f}) / {rp:.2f}({rs:.2f})"
