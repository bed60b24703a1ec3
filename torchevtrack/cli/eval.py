"""``torchevtrack eval``: score a predicted trajectory against the ground truth.

Example:
    torchevtrack eval --gt data/seq0 --pred out/seq0_poses.txt --json
    torchevtrack eval --gt data/seq0 --pred poses_in_us.txt --time-unit us --t-offset -1700000000

With a mesh (``--mesh`` or the sequence directory's ``mesh.ply``) that has no colours and a continuous rotational
symmetry (a plain can), the rotation error with the spin about that axis left out and the failure rule applied to it
are reported too (``*_r_sym_*``, ``failed_sym``), as ``torchevtrack benchmark`` counts them.

Where the prediction has a lost-flag side file beside it (``poses.txt`` -> ``poses.lost.txt``, as ``torchevtrack
track`` writes it), its flags are scored against the failure rule as the benchmark's loss table scores them
(``loss``: :func:`torchevtrack.loss.compare_with_ground_truth`).

Exit status 2 (one line on stderr) when most predicted poses fall outside the ground truth's time range:
the two files then use different time bases (units or origins), which ``--time-unit`` and ``--t-offset`` fix.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchevtrack.io.lost import lost_beside, lost_path
from torchevtrack.io.poses import FORMATS, detect_format, read_poses
from torchevtrack.loss import compare_with_ground_truth
from torchevtrack.mesh import hidden_symmetry_axis, load_mesh
from torchevtrack.metrics import FAIL_R_DEG, FAIL_T_M, FAIL_WINDOW, MESH_POINTS, evaluate, load_mesh_points


TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}  # seconds per unit of a pose file's time column


def retime(t_us: torch.Tensor, unit: str = "s", offset_s: float = 0.0) -> torch.Tensor:
    """Times read from a pose file as seconds (``t_us``, int64 us) when its time column is in ``unit``, shifted by
    ``offset_s`` seconds: ``-> (N,)`` int64 microseconds.

    Example:
        >>> retime(torch.tensor([1_500_000_000_000]), "us", -1.0).tolist()
        [500000]
    """
    if unit not in TIME_UNITS:
        raise ValueError(f"time unit must be one of {', '.join(TIME_UNITS)}, got {unit!r}")
    if unit == "s" and offset_s == 0.0:
        return t_us
    t = t_us.double() * TIME_UNITS[unit] + offset_s * 1e6
    return t.round().to(torch.int64)


def check_overlap(pred_t: torch.Tensor, gt_t: torch.Tensor) -> None:
    """Raise ``ValueError`` (one line) if most prediction times ``(N,)`` lie outside the ground truth's time range."""
    inside = int(((pred_t >= gt_t.min()) & (pred_t <= gt_t.max())).sum())
    if 2 * inside < pred_t.numel():
        def span(t: torch.Tensor) -> str:
            return f"{float(t.min()) / 1e6:.6f} .. {float(t.max()) / 1e6:.6f} s"

        raise ValueError(f"{pred_t.numel() - inside} of {pred_t.numel()} predicted poses ({span(pred_t)}) fall outside "
                         f"the ground truth's time range ({span(gt_t)}): another time base? see --time-unit, "
                         "--t-offset")


def _resolve_gt(gt: Path, mesh: str | None) -> tuple[Path, Path | None]:
    if gt.is_dir():
        poses = gt / "gt_poses.txt"
        if not poses.is_file():
            raise FileNotFoundError(f"sequence directory {gt} has no gt_poses.txt")
        if mesh is None and (gt / "mesh.ply").is_file():
            return poses, gt / "mesh.ply"
        return poses, Path(mesh) if mesh else None
    return gt, Path(mesh) if mesh else None


def _summary(r: dict, gt: Path, pred: Path, mesh: Path | None) -> str:
    def xyz(v: list[float]) -> str:
        return " ".join(f"{a:.3f}" for a in v)

    lines = [
        f"ground truth : {gt}",
        f"prediction   : {pred}",
        f"poses        : {r['n_poses']} evaluated, {r['n_dropped']} dropped (outside the ground-truth time range)",
        f"translation  : RMSE {r['rmse_t_cm']:.3f} cm  sigma {r['std_t_cm']:.3f} cm  "
        f"mean {r['mean_t_cm']:.3f}  median {r['median_t_cm']:.3f}  max {r['max_t_cm']:.3f} cm",
        f"rotation     : RMSE {r['rmse_r_deg']:.3f} deg  sigma {r['std_r_deg']:.3f} deg  "
        f"mean {r['mean_r_deg']:.3f}  median {r['median_r_deg']:.3f}  max {r['max_r_deg']:.3f} deg",
        f"per axis RMSE: t [x y z] {xyz(r['rmse_t_xyz_cm'])} cm   r [x y z] {xyz(r['rmse_r_xyz_deg'])} deg",
    ]
    if r["add_auc"] is None:
        beside = gt.parent / "mesh.ply"
        hint = (f"; --gt {gt.parent} also reads its mesh.ply: ADD / ADD-S, a plain can's spin left out"
                if beside.is_file() else "")
        lines.append(f"ADD / ADD-S  : n/a (no mesh{hint})")
    else:
        lines.append(
            f"ADD / ADD-S  : AUC(0-10 cm) {r['add_auc']:.4f} / {r['adds_auc']:.4f}   "
            f"mean {r['mean_add_cm']:.3f} / {r['mean_adds_cm']:.3f} cm   ({r['n_mesh_points']} points of {mesh})"
        )
    if "rmse_r_sym_deg" in r:
        lines.append(f"rotation sym : RMSE {r['rmse_r_sym_deg']:.3f} deg  median {r['median_r_sym_deg']:.3f}  "
                     f"max {r['max_r_sym_deg']:.3f} deg (the spin about the untextured mesh's symmetry axis left out)")
    rule = f"> {FAIL_T_M * 100:g} cm or > {FAIL_R_DEG:g} deg for {FAIL_WINDOW} samples"
    if r["failed"]:
        lines.append(f"failure      : FAILED at {r['first_failure_s']:.6f} s (pose {r['first_failure_index']}; {rule})")
    else:
        lines.append(f"failure      : no ({rule})")
    if "failed_sym" in r:
        lines.append("failure sym  : " + (f"FAILED at {r['first_failure_sym_s']:.6f} s" if r["failed_sym"] else "no")
                     + " (the same rule on the rotation with the spin left out)")
    if "rmse_v_cm_s" in r:
        lines.append(f"velocity     : RMSE {r['rmse_v_cm_s']:.3f} cm/s, {r['rmse_w_deg_s']:.3f} deg/s")
    if "loss" in r:
        lines.append("lost flags   : " + _loss_line(r["loss"]) + f" ({lost_path(pred)})")
    return "\n".join(lines)


def _loss_line(x: dict) -> str:
    """One line of :func:`compare_with_ground_truth`'s verdict."""
    counts = (f"{x['declarations']} declaration(s), {x['false_alarms']} false alarm(s), {x['recoveries']} "
              "recovery(ies)")
    if x["first_failure_us"] is None:
        return ("no failure, " if x["first_loss_us"] is None else "no failure, declared lost anyway: ") + counts
    if x["missed"]:
        return "the failure was missed: " + counts
    when = (f"{x['delay_us'] / 1e3:.0f} ms after the failure run began" if x["delay_us"] >= 0
            else f"held lost since {-x['delay_us'] / 1e3:.0f} ms before the failure run began")
    return f"the failure was detected {when}: " + counts


def run(args: argparse.Namespace) -> int:
    gt_path, mesh_path = _resolve_gt(Path(args.gt), args.mesh)
    bop = {k: v for k, v in (("fps", args.fps), ("obj_id", args.obj_id)) if v is not None}

    def load(path: Path, fmt: str | None) -> tuple[torch.Tensor, torch.Tensor]:
        is_bop = (fmt or detect_format(path)) == "bop"
        return read_poses(path, format=fmt, **(bop if is_bop else {}))

    gt_t, gt_p = load(gt_path, args.gt_format)
    pred_t, pred_p = load(Path(args.pred), args.pred_format)
    pred_t = retime(pred_t, args.time_unit, args.t_offset)
    check_overlap(pred_t, gt_t)
    points = load_mesh_points(mesh_path) if mesh_path is not None else None
    # as the benchmark: an untextured mesh's spin about its symmetry axis is unobservable, its error reported apart
    axis = hidden_symmetry_axis(load_mesh(mesh_path)) if mesh_path is not None else None
    axis = None if axis is None else torch.as_tensor(axis)
    r = evaluate(pred_t, pred_p, gt_t, gt_p, mesh_points=points, symmetric=args.symmetric, symmetry_axis=axis)
    r["n_mesh_points"] = None if points is None else int(points.shape[0])
    lost = lost_beside(args.pred, pred_t, lambda t: retime(t, args.time_unit, args.t_offset))
    if lost is not None:  # track's lost flags: scored as the benchmark's loss table scores them
        r["loss"] = compare_with_ground_truth(pred_t, lost, pred_p, gt_t, gt_p, symmetry_axis=axis)
    if args.json:
        print(json.dumps(r))
    else:
        print(_summary(r, gt_path, Path(args.pred), mesh_path))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "eval",
        help="score predicted poses against ground truth",
        description=(
            "Score a predicted trajectory against the ground truth: translation / rotation RMSE and sigma, "
            "ADD and ADD-S AUC on 0..10 cm (with a mesh), EDOPT failure rule. The ground truth is "
            "interpolated at the prediction times; predictions outside its time range are dropped. A lost-flag "
            "side file beside the prediction (poses.txt -> poses.lost.txt, as track writes it) is scored too."
        ),
    )
    p.add_argument("--gt", required=True, help="ground-truth pose file, or a sequence directory (gt_poses.txt, mesh.ply)")
    p.add_argument("--pred", required=True, help="predicted pose file (TUM .txt, CSV .csv, BOP .json)")
    p.add_argument("--mesh", help=f"mesh file for ADD / ADD-S (vertices, at most {MESH_POINTS} points, as the "
                   "benchmark)")
    p.add_argument("--symmetric", action="store_true", help="symmetric object: ADD(-S) (add_s_auc) uses ADD-S")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    p.add_argument("--fps", type=float, help="frame rate giving the times of BOP scene_gt.json frames")
    p.add_argument("--obj-id", type=int, help="object id to read from BOP scene_gt.json files")
    p.add_argument("--time-unit", choices=tuple(TIME_UNITS), default="s",
                   help="unit of the prediction file's time column (default s, as TUM)")
    p.add_argument("--t-offset", type=float, default=0.0, metavar="SECONDS",
                   help="add this to the prediction times (after --time-unit) to reach the ground truth's time base")
    p.add_argument("--gt-format", choices=FORMATS, help="override the ground-truth format detection")
    p.add_argument("--pred-format", choices=FORMATS, help="override the prediction format detection")
    p.set_defaults(func=run)
