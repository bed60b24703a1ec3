"""``torchevtrack info DIR``: what a sequence directory holds (events, rate, duration; with ``gt_poses.txt`` also the
speeds and the pose range)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchevtrack.camera import Camera
from torchevtrack.geometry import quat_conj, quat_log, quat_mul
from torchevtrack.io.events_h5 import events_h5_summary
from torchevtrack.io.poses import read_tum
from torchevtrack.synth.sequence import TEXTURED_MESH
from torchevtrack.synth.trajectory import motion_stats


def sequence_info(directory: str | Path) -> dict:
    """Summary of a sequence directory; reads only the event count and end times from ``events.h5``.

    ``events.h5`` and ``camera.json`` are required (FileNotFoundError naming the missing one); ``gt_poses.txt`` is
    not (a recording): without it the summary has ``gt_poses = 0`` and no speeds or pose range."""
    d = Path(directory)
    if not d.is_dir():
        raise FileNotFoundError(f"sequence directory not found: {d}")
    for name in ("events.h5", "camera.json"):
        if not (d / name).is_file():
            raise FileNotFoundError(f"sequence {d} lacks {name}")
    camera = Camera.load(d / "camera.json")
    ev = events_h5_summary(d / "events.h5")
    duration_us = ev["t_last_us"] - ev["t_first_us"]
    info = {
        "directory": str(d),
        "camera": camera.to_dict(),
        "events": ev["n"],
        "events_t_first_us": ev["t_first_us"],
        "events_t_last_us": ev["t_last_us"],
        "events_duration_s": duration_us / 1e6,
        "events_per_s": ev["n"] / (duration_us / 1e6) if duration_us > 0 else 0.0,
        "gt_poses": 0,
    }
    if (d / "gt_poses.txt").is_file():
        info.update(_ground_truth_info(d / "gt_poses.txt", camera))
    if (d / "meta.json").is_file():
        meta = json.loads((d / "meta.json").read_text())
        info["meta"] = {k: meta[k] for k in ("object", "motion", "seed") if k in meta}
        info["effects"] = sensor_effects(meta)
    info["textured_mesh"] = TEXTURED_MESH if (d / TEXTURED_MESH).is_file() else None
    return info


def _ground_truth_info(path: Path, camera: Camera) -> dict:
    """The ground truth's pose count, span, rate, pose range and (two poses or more) speeds."""
    t_us, poses = read_tum(path)
    span_s = float(t_us[-1] - t_us[0]) / 1e6
    rel = quat_log(quat_mul(poses[:, 3:], quat_conj(poses[:1, 3:]))).norm(dim=-1)  # rotation from the first pose
    info = {
        "gt_poses": int(t_us.numel()),
        "gt_duration_s": span_s,
        "gt_rate_hz": (t_us.numel() - 1) / span_s if t_us.numel() > 1 else 0.0,
        "pose_range": {
            "t_min_m": poses[:, :3].amin(0).tolist(),
            "t_max_m": poses[:, :3].amax(0).tolist(),
            "rotation_from_start_max_deg": float(torch.rad2deg(rel.max())),
        },
    }
    if t_us.numel() > 1:
        info["speeds"] = motion_stats(t_us, poses, camera)
    return info


def sensor_effects(meta: dict) -> dict:
    """The simulated world of a generated sequence from its ``meta.json``: contrast threshold and its spread,
    noise rate, refractory period, hot pixels (count, rate), hand (occluded silhouette fraction), texture,
    depth range, an excursion out of the view (``leave_view``: start and time away, s). Effects the generator did not
    record (older or standard sequences) take their off values."""
    gen = meta.get("generator", {})
    esim = gen.get("esim", {})
    occ = meta.get("occluder")
    return {
        "contrast_threshold": esim.get("C"),
        "sigma_c": esim.get("sigma_C"),
        "noise_rate_hz": esim.get("noise_rate_hz", 0.0),
        "refractory_us": esim.get("refractory_us", 0),
        "hot_pixels": esim.get("hot_pixels", 0),
        "hot_pixel_rate_hz": esim.get("hot_pixel_rate_hz"),
        "occluder": "none" if occ is None else occ["kind"],
        "occluded_fraction": None if occ is None else occ["occluded_fraction"],
        "texture": (meta.get("texture") or {}).get("kind", "none"),
        "depth_range_m": gen.get("depth_range_m", [0.3, 0.7]),
        "leave_view": meta.get("leave_view"),
    }


def _fmt_stats(s: dict, unit: str) -> str:
    return (f"median {s['median']:.0f} {unit} (p10 {s['p10']:.0f}, p90 {s['p90']:.0f}, "
            f"max {s['max']:.0f}, mean {s['mean']:.0f})")


def _event_file_info(args: argparse.Namespace) -> int:
    """``info FILE``: a summary of any readable event file (one streamed pass)."""
    from torchevtrack.io.formats import open_events

    s = open_events(args.directory).summary()
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    size = f"{s['width']}x{s['height']}" if s["width"] is not None and s["height"] is not None else "not stored"
    print(f"event file {s['path']} ({s['format']})")
    print(f"events     {s['events']} over {s['duration_s']:.3f} s ({s['events_per_s'] / 1e6:.3f} Mev/s), "
          f"t {s['t_first_us']} .. {s['t_last_us']} us, {100 * s['on_fraction']:.1f}% ON")
    print(f"sensor     {size}; x in {s['x_range']}, y in {s['y_range']}")
    return 0


def run(args: argparse.Namespace) -> int:
    if Path(args.directory).is_file():
        return _event_file_info(args)
    if not Path(args.directory).exists():
        raise FileNotFoundError(f"no such sequence directory or event file: {args.directory}")
    info = sequence_info(args.directory)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    c = info["camera"]
    print(f"sequence   {info['directory']}")
    if "meta" in info:
        print("generated  " + ", ".join(f"{k} {v}" for k, v in info["meta"].items()))
        e = info["effects"]
        hot = f"{e['hot_pixels']} hot pixels" + (f" at {e['hot_pixel_rate_hz']:g} Hz" if e["hot_pixels"] else "")
        print(f"sensor     C {e['contrast_threshold']}, sigma_C {e['sigma_c']}, noise {e['noise_rate_hz']:g} Hz/pixel, "
              f"refractory {e['refractory_us']} us, {hot}")
        occ = e["occluded_fraction"]
        hand = "none" if occ is None else (f"{e['occluder']}, hides {100 * occ['median']:.0f} % of the silhouette "
                                           f"(median; {100 * occ['min']:.0f}-{100 * occ['max']:.0f} %)")
        lo, hi = e["depth_range_m"]
        model = f" (its model: {info['textured_mesh']})" if info["textured_mesh"] else ""
        away = "" if e["leave_view"] is None else \
            f"; leaves the view at {e['leave_view']['start_s']:g} s for {e['leave_view']['away_s']:g} s"
        print(f"world      occluder {hand}; texture {e['texture']}{model}; depth range {lo:g}-{hi:g} m{away}")
    print(f"camera     {c['width']}x{c['height']}, fx {c['fx']:g}, fy {c['fy']:g}, cx {c['cx']:g}, cy {c['cy']:g}")
    print(f"events     {info['events']} over {info['events_duration_s']:.3f} s "
          f"({info['events_per_s'] / 1e6:.3f} Mev/s)")
    if not info["gt_poses"]:
        print("gt poses   none (no gt_poses.txt: track it with --init)")
        return 0
    print(f"gt poses   {info['gt_poses']} over {info['gt_duration_s']:.3f} s ({info['gt_rate_hz']:.0f} Hz)")
    if "speeds" in info:
        print("img speed  " + _fmt_stats(info["speeds"]["image_speed_px_s"], "px/s"))
        print("ang speed  " + _fmt_stats(info["speeds"]["angular_speed_deg_s"], "deg/s"))
    r = info["pose_range"]
    for axis, lo, hi in zip("xyz", r["t_min_m"], r["t_max_m"]):
        print(f"t{axis}         {lo:+.3f} .. {hi:+.3f} m")
    print(f"rotation   up to {r['rotation_from_start_max_deg']:.1f} deg from the first pose")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("info", help="summarise a sequence directory or an event file",
                              description="Events, event rate, duration, image and angular speeds (from the "
                              "ground truth, if there is one) and the pose range of a sequence directory.")
    p.add_argument("directory", help="sequence directory, or an event file of any format `convert` reads")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)
