"""Per-factor report of a benchmark run on a suite: how the error depends on motion, camera, noise, hand, texture,
object size and the object itself, and every sequence's error against time in one figure.

:func:`sequence_factors` reads each sequence's factors from the suite's ``suite.json``
(:func:`torchevtrack.synth.suite.write_suite_json`) or, without it, from the sequences' ``meta.json`` and
``camera.json``. :func:`factor_tables` groups the results of :func:`torchevtrack.benchmark.run_benchmark` by
each factor: per value and method, the number of runs (every start draw), the mean and median translation and the
mean rotation RMSE, the mean ADD-S AUC and the failed runs (EDOPT rule, also with a symmetry axis left out).
:func:`write_suite_report` writes ``factors.md`` and ``plots/suite_errors.png`` next to the benchmark's own report.

Example:
    >>> res = {"results": {"full": {"a": {"metrics": {"rmse_t_cm": 1.0, "rmse_r_deg": 2.0, "adds_auc": 0.9,
    ...                                                "failed": False}}}}}
    >>> print(factor_tables(res, {"a": {"motion": "turn"}}, factors_order=("motion",)).splitlines()[2])
    ## Overall
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchevtrack.loss import LOSS_DELAY_US
from torchevtrack.metrics import sym_failed, sym_rmse_r_deg

__all__ = ["FACTORS", "factor_tables", "noise_level", "sequence_factors", "suite_error_plot", "write_suite_report"]

FACTORS = {
    "motion": "motion group",
    "camera": "camera",
    "noise": "noise level",
    "hand": "hand",
    "texture": "texture",
    "size": "object size",
    "object": "object",
}
"""The factors of the report (key: heading)."""

_CAMERA_NAMES = {(346, 260): "davis346", (640, 480): "vga", (1280, 720): "hd"}


def noise_level(rate_hz: float) -> str:
    """Bucket of a background-noise rate (events per pixel per second): ``none`` (0), ``low`` (<= 0.2 Hz,
    a sensor in good light), ``medium`` (<= 1 Hz), ``high`` (above)."""
    if rate_hz <= 0:
        return "none"
    return "low" if rate_hz <= 0.2 else "medium" if rate_hz <= 1.0 else "high"


def sequence_factors(bench_dir: str | Path, names) -> dict[str, dict]:
    """``{name: {factor: value}}`` for the sequences ``names`` of ``bench_dir`` (keys of :data:`FACTORS`).

    From ``bench_dir/suite.json`` when it lists the sequence, else from its ``meta.json`` (motion, noise, hand,
    texture) and ``camera.json`` (camera preset name, or ``WxH``) and the mesh's bounding box (size).
    """
    from torchevtrack.synth.suite import object_label, read_suite_json, size_class

    root = Path(bench_dir)
    suite = read_suite_json(root)
    listed = {e["name"]: e for e in (suite or {}).get("sequences", [])}
    out = {}
    for name in names:
        e = listed.get(name)
        if e is not None:
            out[name] = {"motion": e["motion"], "camera": e["camera"], "noise": noise_level(e["noise_rate"]),
                         "hand": e["occluder"], "texture": e["texture"], "size": e.get("size") or "?",
                         "object": object_label(e["object"]) if e.get("object") else "?"}
            continue
        d = root / name
        meta = json.loads((d / "meta.json").read_text()) if (d / "meta.json").is_file() else {}
        cam = json.loads((d / "camera.json").read_text()) if (d / "camera.json").is_file() else {}
        size = "?"
        if (d / "mesh.ply").is_file():
            import trimesh

            size = size_class(trimesh.load(d / "mesh.ply", force="mesh", process=False).extents)
        wh = (cam.get("width"), cam.get("height"))
        out[name] = {
            "motion": meta.get("motion", "?"),
            "camera": _CAMERA_NAMES.get(wh, f"{wh[0]}x{wh[1]}"),
            "noise": noise_level(meta.get("generator", {}).get("esim", {}).get("noise_rate_hz", 0.0)),
            "hand": (meta.get("occluder") or {}).get("kind", "none"),
            "texture": (meta.get("texture") or {}).get("kind", "none"),
            "size": size,
            "object": object_label(meta["object"]) if meta.get("object") else "?",
        }
    return out


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _summary(rows: list[dict], sym: bool, loss: bool) -> list[str]:
    t = [r["rmse_t_cm"] for r in rows]
    cells = [f"{np.mean(t):.2f}", f"{np.median(t):.2f}", f"{np.mean([r['rmse_r_deg'] for r in rows]):.2f}",
             f"{100 * np.mean([r['adds_auc'] for r in rows]):.1f}",
             f"{sum(bool(r['failed']) for r in rows)}/{len(rows)}"]
    if sym:  # the symmetry axis left out where a run has one, the whole rotation elsewhere
        cells += [f"{np.mean([sym_rmse_r_deg(r) for r in rows]):.2f}",
                  f"{sum(sym_failed(r) for r in rows)}/{len(rows)}"]
    if loss:  # the lost flags against the loss table's rule (the held runs' rule)
        verdicts = [r.get("loss") for r in rows]
        if any(v is None for v in verdicts):
            cells.append("–")
        else:
            failed = [v for v in verdicts if v["first_failure_us"] is not None]
            soon = sum(v["delay_us"] is not None and v["delay_us"] <= LOSS_DELAY_US for v in failed)
            cells.append(f"{sum(not v['missed'] for v in failed)}/{len(failed)} ({soon})")
    return cells


def _runs(results: dict) -> dict[str, dict[str, list[dict]]]:
    """``{method: {sequence: [metrics of each run]}}``: a method's every start draw when it ran trials, else the one
    run of each sequence (a method scored from another tracker's pose files has no trials)."""
    trials = results.get("trials") or {}
    return {m: {s: list(trials[m][s]) if s in trials.get(m, {}) else [{**r["metrics"], "loss": r.get("loss")}]
                for s, r in seqs.items()}
            for m, seqs in results["results"].items()}


def _held_by_motion_and_camera(runs: dict[str, dict[str, list[dict]]], factors: dict[str, dict]) -> list[str]:
    """Markdown lines: held runs / runs per motion group (rows, per method) and camera (columns, then all)."""
    def value(s: str, f: str) -> str:
        return str(factors[s].get(f, "?"))

    cams = sorted({value(s, "camera") for s in factors})
    lines = ["## Held runs by motion group and camera", "", _row(["motion group", "method"] + cams + ["all"]),
             _row(["---"] * (3 + len(cams)))]
    for motion in sorted({value(s, "motion") for s in factors}):
        for m, seqs in runs.items():
            cells = []
            for cam in cams + [None]:
                rows = [r for s in factors if value(s, "motion") == motion and cam in (None, value(s, "camera"))
                        for r in seqs.get(s, [])]
                cells.append(f"{sum(not sym_failed(r) for r in rows)}/{len(rows)}" if rows else "–")
            if any(c != "–" for c in cells):
                lines.append(_row([motion, m] + cells))
    return lines + [""]


def factor_tables(results: dict, factors: dict[str, dict], *, factors_order=tuple(FACTORS)) -> str:
    """Markdown: an overall table, then one table per factor (rows: the factor's values, sorted; per method the
    runs (sequences x start draws), the mean and median e_p RMSE (cm), mean e_r RMSE (deg), mean ADD-S AUC (%) and
    failed / runs; where a run has a symmetry axis also the mean e_r and failed runs with the rotation about that
    axis left out, as the trials table of :func:`torchevtrack.benchmark.table_markdown` counts them); then, when
    ``factors_order`` holds both ``motion`` and ``camera``, the held runs (not failed; by the symmetry rule where a
    run has one) per motion group and camera.

    Every start draw counts (``results["trials"]``) when the run had them, else each sequence's one run
    (``results["results"][method][seq]["metrics"]``). Read from each run: ``rmse_t_cm``, ``rmse_r_deg``,
    ``adds_auc``, ``failed`` and, where present, ``rmse_r_sym_deg``, ``failed_sym`` and the benchmark's loss verdict
    ``loss`` (then a column: failed runs the lost flags detected / failed runs, and those within
    :data:`~torchevtrack.loss.LOSS_DELAY_US`).

    Args:
        results: the dict of :func:`torchevtrack.benchmark.run_benchmark`.
        factors: ``{sequence: {factor: value}}`` (:func:`sequence_factors`); sequences without results are
            skipped.
        factors_order: the factors to tabulate, in order (keys of :data:`FACTORS` or any key of ``factors``).
    """
    per_method = results.get("results") if isinstance(results, dict) else None
    if not isinstance(per_method, dict) or not per_method:
        raise ValueError("results must be the dict of run_benchmark (a non-empty 'results')")
    runs = _runs(results)
    methods = list(runs)
    sym = any("failed_sym" in r for seqs in runs.values() for rs in seqs.values() for r in rs)
    head = ["mean e_p (cm)", "median e_p (cm)", "mean e_r (deg)", "ADD-S AUC (%)", "failed"]
    if sym:
        head += ["mean e_r, sym. (deg)", "failed, sym."]
    loss = any(r.get("loss") is not None for seqs in runs.values() for rs in seqs.values() for r in rs)
    if loss:
        head += [f"failures flagged (in {LOSS_DELAY_US // 1000} ms)"]
    lines = ["# Results by factor", ""]

    def table(title: str, groups: dict[str, list[str]]) -> None:
        lines.extend([f"## {title}", ""])
        lines.append(_row(["value", "method", "runs"] + head))
        lines.append(_row(["---"] * (3 + len(head))))
        for value in sorted(groups, key=str):
            for m in methods:
                rows = [r for s in groups[value] for r in runs[m].get(s, [])]
                if rows:
                    lines.append(_row([value, m, len(rows)] + _summary(rows, sym, loss)))
        lines.append("")

    names = [s for s in factors if any(s in runs[m] for m in methods)]
    table("Overall", {"all": names})
    for f in factors_order:
        groups: dict[str, list[str]] = {}
        for s in names:
            groups.setdefault(str(factors[s].get(f, "?")), []).append(s)
        table(FACTORS.get(f, f).capitalize(), groups)
    if "motion" in factors_order and "camera" in factors_order:  # where the losses sit: the two factors together
        lines += _held_by_motion_and_camera(runs, {s: factors[s] for s in names})
    lines.append("runs: sequences x start draws; e_p, e_r: RMSE of the translation (cm) and rotation (deg) error over "
                 "a run's updates, averaged over the runs of the row (median e_p: over them); failed: runs failed by "
                 "the EDOPT rule" + ("; sym.: the rotation about the symmetry axis of a symmetric untextured object "
                                     "left out, for the error and the rule (other runs count whole)" if sym else "")
                 + ("; failures flagged: failed runs (the held runs' rule) the lost flags detected / failed runs, "
                    f"in brackets those flagged within {LOSS_DELAY_US // 1000} ms (the benchmark's loss table)"
                    if loss else "")
                 + ". Noise level: none 0, low <= 0.2, medium <= 1, high > 1 events per pixel per second.")
    return "\n".join(lines) + "\n"


def suite_error_plot(curves: dict[str, tuple], path: str | Path, *, title: str | None = None) -> Path:
    """One small panel per sequence: translation error (cm, left axis) and rotation error (deg, right axis)
    against time (s). ``curves``: ``{sequence: (t_s (N,), te_cm (N,), re_deg (N,))}``. Returns the PNG path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    if not curves:
        raise ValueError("curves is empty")
    n = len(curves)
    cols = min(4, n)
    rows = -(-n // cols)
    fig = Figure(figsize=(3.2 * cols, 2.0 * rows + 0.6), dpi=90, layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, (name, (t, te, re)) in zip(axes, sorted(curves.items())):
        ax.plot(t, te, lw=0.8, color="tab:blue")
        ax.set_title(name, fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_ylabel("cm", fontsize=6, color="tab:blue")
        ax2 = ax.twinx()
        ax2.plot(t, re, lw=0.8, color="tab:red")
        ax2.tick_params(labelsize=6)
        ax2.set_ylabel("deg", fontsize=6, color="tab:red")
    for ax in axes[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def write_suite_report(results: dict, bench_dir: str | Path, out_dir: str | Path,
                       method: str | None = None) -> tuple[Path, Path]:
    """Write ``out_dir/factors.md`` (:func:`factor_tables`) and ``out_dir/plots/suite_errors.png`` (every
    sequence's error against time for ``method``, default ``"no_ukf"``, the default config, when run, else the first
    method), from a finished run's ``results`` and its ``poses/`` files. Returns the two paths."""
    from torchevtrack.io.poses import read_tum
    from torchevtrack.metrics import per_pose_errors

    out = Path(out_dir)
    per_method = results["results"]
    names = sorted({s for m in per_method.values() for s in m})
    factors = sequence_factors(bench_dir, names)
    md = out / "factors.md"
    md.write_text(factor_tables(results, factors))
    method = method or ("no_ukf" if "no_ukf" in per_method else next(iter(per_method)))
    curves = {}
    for name, r in per_method[method].items():
        t_us, poses = read_tum(out / r["pose_file"])
        gt_t, gt = read_tum(Path(bench_dir) / name / "gt_poses.txt")
        e = per_pose_errors(t_us, poses, gt_t, gt)
        curves[name] = (((e["t_us"] - gt_t[0]).double() / 1e6).numpy(), (e["te"] * 100.0).numpy(),
                        np.degrees(e["re"].numpy()))
    png = suite_error_plot(curves, out / "plots" / "suite_errors.png", title=f"error against time ({method})")
    return md, png
