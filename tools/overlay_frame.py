"""Overlay a sequence's events on the object rendered at its ground-truth pose (a visual sanity check).

Events within +-window/2 of the chosen time are drawn over the shaded grey render: ON red, OFF blue
(a pixel with both shows the later one). They should hug the object's outline and its interior edges.

Usage:
    PYOPENGL_PLATFORM=egl python tools/overlay_frame.py SEQUENCE_DIR --time 1.5 [--window-ms 2] [--out x.png]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchevtrack.geometry import interpolate_poses  # noqa: E402
from torchevtrack.render import Renderer  # noqa: E402
from torchevtrack.synth.sequence import Sequence  # noqa: E402


def overlay(seq: Sequence, t_us: int, window_us: int, scale: int = 1) -> tuple[np.ndarray, int]:
    """RGB uint8 image ``(H * scale, W * scale, 3)``: grey render at ``t_us`` with the events of the window
    ``[t_us - window_us / 2, t_us + window_us / 2)``; also returns the number of events drawn."""
    lo, hi = int(seq.gt_t_us[0]), int(seq.gt_t_us[-1])
    if not lo <= t_us <= hi:
        raise ValueError(f"time {t_us / 1e6:.6f} s is outside the ground truth [{lo / 1e6:.6f}, {hi / 1e6:.6f}] s")
    pose = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t_us]))
    background = float(seq.meta.get("generator", {}).get("background", 0.2))
    with Renderer(seq.mesh, seq.camera, background=background) as r:
        gray = r.render(pose).gray[0].numpy()
    rgb = np.repeat((gray * 255).astype(np.uint8)[..., None], 3, axis=-1)
    ev = seq.events.slice_time(t_us - window_us // 2, t_us + window_us // 2)
    x, y, p = ev.x.long().numpy(), ev.y.long().numpy(), ev.p.numpy().astype(bool)
    rgb[y, x] = np.where(p[:, None], np.array([255, 0, 0], np.uint8), np.array([0, 64, 255], np.uint8))
    return rgb.repeat(scale, 0).repeat(scale, 1), len(ev)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", help="sequence directory")
    ap.add_argument("--time", type=float, required=True, help="seconds")
    ap.add_argument("--window-ms", type=float, default=2.0, help="event window centred on --time, milliseconds")
    ap.add_argument("--scale", type=int, default=1, help="integer upscaling of the output image")
    ap.add_argument("--out", help="output PNG (default: SEQUENCE/overlay_<time>.png)")
    args = ap.parse_args(argv)
    seq = Sequence.load(args.sequence)
    img, n = overlay(seq, int(round(args.time * 1e6)), int(round(args.window_ms * 1e3)), args.scale)
    out = Path(args.out) if args.out else Path(args.sequence) / f"overlay_{args.time:.3f}.png"
    iio.imwrite(out, img)
    print(f"{out}: {n} events in {args.window_ms:g} ms around {args.time:g} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
