"""Visual checks of a tracker: mesh contours over EROS images, overlay videos and error plots.

Images are numpy RGB ``uint8`` arrays ``(H, W, 3)``. Inputs may be torch tensors or numpy arrays.
Needs the optional ``viz`` extra (matplotlib, imageio; MP4 also needs ``imageio-ffmpeg``).

* :func:`contour_mask` -- silhouette (and optionally internal depth-edge) pixels of a depth render.
* :func:`overlay` -- EROS in grey with coloured contours and an optional legend.
* :func:`eros_frames` / :func:`iter_eros` -- EROS surfaces at requested times (exact, vectorised).
* :func:`overlay_frames` / :func:`iter_overlay_frames` -- tracked (green) and ground-truth (magenta)
  contours over the EROS of a stream at each requested time.
* :func:`save_video` -- GIF (imageio/pillow) or MP4 (imageio-ffmpeg), chosen by the extension.
* :func:`plot_errors` / :func:`plot_errors_multi` -- translation / rotation error against time (PNG).

Example:
    >>> import numpy as np
    >>> from torchevtrack.viz import contour_mask, overlay
    >>> depth = np.zeros((6, 7), np.float32); depth[1:5, 2:6] = 0.5
    >>> ring = contour_mask(depth, thickness=1)
    >>> int(ring.sum()), bool(ring[2, 3])  # the 4 x 4 square's border, not its inside
    (12, False)
    >>> overlay(np.zeros((6, 7)), [(ring, (0, 255, 0))])[1, 2].tolist()
    [0, 255, 0]
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.geometry import interpolate_poses
from torchevtrack.stages.eros import EROS

__all__ = [
    "GT_COLOUR",
    "PRED_COLOUR",
    "VIDEO_EXTENSIONS",
    "contour_mask",
    "eros_frames",
    "iter_eros",
    "iter_overlay_frames",
    "overlay",
    "overlay_frames",
    "plot_errors",
    "plot_errors_multi",
    "save_video",
]

PRED_COLOUR = (0, 255, 0)  # tracked pose: green
GT_COLOUR = (255, 0, 255)  # ground truth: magenta
VIDEO_EXTENSIONS = (".gif", ".mp4")
_EROS_CHUNK = 100_000  # events per EROS update (memory ~0.4 kB per event at k = 7)


def _numpy(a, name: str) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        return a.detach().cpu().numpy()
    if isinstance(a, np.ndarray):
        return a
    raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(a).__name__}")


# -- contours and overlays ------------------------------------------------------------------------
def _neighbour(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``a`` shifted so that ``out[v, u] = a[v + dy, u + dx]``, edge values repeated at the border."""
    p = np.pad(a, 1, mode="edge")
    h, w = a.shape
    return p[1 + dy: 1 + dy + h, 1 + dx: 1 + dx + w]


def contour_mask(depth, *, thickness: int = 2, depth_jump: float | None = None) -> np.ndarray:
    """Contour pixels of a depth render: where the object meets the background.

    A pixel is on the silhouette contour when it and one of its 4-neighbours lie on different sides
    (``depth > 0`` vs ``depth == 0``). ``thickness=1`` keeps only the object side (a 1 px ring, closed
    under 4-connectivity); ``thickness=2`` also keeps the background side (a 2 px ring, closed under
    8-connectivity). With ``depth_jump`` (metres), internal occlusion edges are added the same way:
    object pixels whose object 4-neighbour is farther by more than ``depth_jump`` (the near side; with
    ``thickness=2`` the far side too). The image border is not an edge (edge pixels are repeated).

    Shape:
        depth: ``(H, W)`` float, metres, 0 where no surface is seen. Returns ``(H, W)`` bool.
    """
    d = _numpy(depth, "depth")
    if d.ndim != 2 or not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"depth must be a 2-D float image (H, W), got {d.dtype} {d.shape}")
    if not np.isfinite(d).all() or (d < 0).any():
        raise ValueError("depth must be finite and >= 0 (0 = background)")
    if thickness not in (1, 2):
        raise ValueError(f"thickness must be 1 or 2, got {thickness!r}")
    if depth_jump is not None and not (math.isfinite(depth_jump) and depth_jump > 0):
        raise ValueError(f"depth_jump must be a positive number of metres or None, got {depth_jump!r}")
    fg = d > 0
    mask = np.zeros_like(fg)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        n = _neighbour(d, dy, dx)
        nfg = n > 0
        mask |= fg & ~nfg
        if thickness == 2:
            mask |= ~fg & nfg
        if depth_jump is not None:
            both = fg & nfg
            mask |= both & (n - d > depth_jump)
            if thickness == 2:
                mask |= both & (d - n > depth_jump)
    return mask


def _check_colour(c, name: str) -> np.ndarray:
    rgb = np.asarray(c)
    if rgb.shape != (3,) or not np.all((rgb >= 0) & (rgb <= 255)) or not np.all(rgb == np.round(rgb)):
        raise ValueError(f"{name} must be an (r, g, b) triple of integers in [0, 255], got {c!r}")
    return rgb.astype(np.uint8)


def _draw_legend(img: np.ndarray, legend: Sequence[tuple[str, tuple[int, int, int] | None]]) -> np.ndarray:
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default()
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    x, y, pad = 3, 3, 2
    for text, colour in legend:
        fill = (255, 255, 255) if colour is None else tuple(int(v) for v in colour)
        tx = x if colour is None else x + 10
        x0, y0, x1, y1 = draw.textbbox((tx, y), text, font=font)
        draw.rectangle((x - 1, y0 - pad, x1 + pad, y1 + pad), fill=(0, 0, 0))
        if colour is not None:  # a swatch of the exact colour (the text itself is anti-aliased)
            mid = (y0 + y1) // 2
            draw.rectangle((x + 1, mid - 3, x + 6, mid + 3), fill=fill)
        draw.text((tx, y), text, font=font, fill=fill)
        y = y1 + 2 * pad + 1
    return np.asarray(pil).copy()


def overlay(eros, contours: Sequence[tuple[object, tuple[int, int, int]]] = (), *,
            legend: Sequence[tuple[str, tuple[int, int, int] | None]] | None = None,
            brightness: float = 0.8) -> np.ndarray:
    """Draw contours over an EROS surface.

    The surface is shown in grey, ``round(255 * brightness * clip(eros, 0, 1))`` (dark where no
    recent events); each contour mask is painted in its colour, later ones on top. ``legend`` lines
    ``(text, rgb)`` are written at the top-left on black boxes, each after a swatch of its colour
    (``rgb=None``: plain white text, no swatch).

    Shape:
        eros: ``(H, W)`` float in ``[0, 1]``; each mask ``(H, W)`` bool. Returns ``(H, W, 3)`` uint8.
    """
    s = _numpy(eros, "eros")
    if s.ndim != 2 or not np.issubdtype(s.dtype, np.floating):
        raise ValueError(f"eros must be a 2-D float image (H, W), got {s.dtype} {s.shape}")
    if not 0.0 <= brightness <= 1.0:
        raise ValueError(f"brightness must be in [0, 1], got {brightness!r}")
    grey = np.round(255.0 * brightness * np.clip(np.nan_to_num(s, nan=0.0), 0.0, 1.0)).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=-1)
    for i, item in enumerate(contours):
        if not isinstance(item, (tuple, list)) or len(item) != 2:
            raise ValueError(f"contours[{i}] must be a (mask, (r, g, b)) pair")
        mask = _numpy(item[0], f"contours[{i}] mask")
        if mask.dtype != np.bool_ or mask.shape != s.shape:
            raise ValueError(f"contours[{i}] mask must be bool with the eros shape {s.shape}, "
                             f"got {mask.dtype} {mask.shape}")
        img[mask] = _check_colour(item[1], f"contours[{i}] colour")
    if legend:
        for i, (_, colour) in enumerate(legend):
            if colour is not None:
                _check_colour(colour, f"legend[{i}] colour")
        img = _draw_legend(img, legend)
    return img


# -- EROS at sample times -------------------------------------------------------------------------
def _check_times(times_us) -> torch.Tensor:
    t = torch.as_tensor(times_us)
    if t.dtype not in (torch.int64, torch.int32) or t.ndim != 1:
        raise TypeError(f"times_us must be a 1-D integer (microseconds) sequence, got {t.dtype} {tuple(t.shape)}")
    if (t[1:] < t[:-1]).any():
        raise ValueError("times_us must be non-decreasing")
    return t.to(torch.int64)


def iter_eros(events: EventStream, camera: Camera, times_us, *, kernel_size: int = 7,
              decay: float = 0.3) -> Iterator[torch.Tensor]:
    """Yield the EROS surface of the stream at each time in ``times_us`` (non-decreasing, us).

    The surface at time ``t`` has seen every event with timestamp ``< t``, fed in stream order from
    the first event in packets of at most 100k (exact: same as a per-event sequential EROS).

    Shape: yields ``(H, W)`` float32 copies, ``H, W`` the camera size.
    """
    if not isinstance(events, EventStream):
        raise TypeError(f"events must be an EventStream, got {type(events).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    times = _check_times(times_us)
    eros = EROS(camera.height, camera.width, kernel_size=kernel_size, decay=decay)
    ends = torch.searchsorted(events.t, times, right=False).tolist()
    start = 0
    for end in ends:
        for i in range(start, end, _EROS_CHUNK):
            j = min(i + _EROS_CHUNK, end)
            eros(events.x[i:j], events.y[i:j])
        start = max(start, end)
        yield eros.surface[0].clone()


def eros_frames(events: EventStream, camera: Camera, times_us, kernel_size: int = 7,
                decay: float = 0.3) -> torch.Tensor:
    """EROS surfaces at the requested times (see :func:`iter_eros`).

    Shape: ``times_us (K,)`` int64 us -> ``(K, H, W)`` float32 in ``[0, 1]``.
    """
    frames = list(iter_eros(events, camera, times_us, kernel_size=kernel_size, decay=decay))
    if not frames:
        return torch.zeros(0, camera.height, camera.width)
    return torch.stack(frames)


# -- overlay videos -------------------------------------------------------------------------------
def _check_trajectory(traj, name: str) -> tuple[torch.Tensor, torch.Tensor]:
    if not isinstance(traj, (tuple, list)) or len(traj) != 2:
        raise TypeError(f"{name} must be a (t_us (N,), poses (N, 7)) pair")
    t = torch.as_tensor(traj[0])
    p = torch.as_tensor(traj[1], dtype=torch.float64)
    if t.dtype not in (torch.int64, torch.int32) or t.ndim != 1 or t.numel() == 0:
        raise ValueError(f"{name} times must be a non-empty 1-D integer (microseconds) tensor, "
                         f"got {t.dtype} {tuple(t.shape)}")
    if p.shape != (t.shape[0], 7):
        raise ValueError(f"{name} poses must have shape ({t.shape[0]}, 7), got {tuple(p.shape)}")
    if (t[1:] < t[:-1]).any():
        raise ValueError(f"{name} times must be sorted")
    return t.to(torch.int64), p


def _poses_at(traj: tuple[torch.Tensor, torch.Tensor], times: torch.Tensor) -> list[torch.Tensor | None]:
    """Interpolated pose at each time inside the trajectory's range, ``None`` outside (no extrapolation)."""
    t, p = traj
    inside = (times >= t[0]) & (times <= t[-1])
    out: list[torch.Tensor | None] = [None] * times.numel()
    if inside.any():
        for i, pose in zip(inside.nonzero()[:, 0].tolist(), interpolate_poses(t, p, times[inside])):
            out[i] = pose
    return out


def iter_overlay_frames(events: EventStream, camera: Camera, mesh, pred, times_us, gt=None, *,
                        kernel_size: int = 7, decay: float = 0.3, depth_jump: float | None = None,
                        thickness: int = 2, legend: bool = True, brightness: float = 0.8) -> Iterator[np.ndarray]:
    """Yield, for each time, the EROS of the stream with the mesh contour at the tracked pose (green,
    on top) and at the ground-truth pose (magenta).

    Poses come from the trajectories by interpolation (linear translation, slerp rotation). Nothing is
    extrapolated: at a time outside a trajectory's range that contour is skipped (the legend says
    "no pose"), the frame itself is still produced.

    Args:
        events: time-sorted events inside the camera's sensor.
        camera: the full-frame camera.
        mesh: a ``trimesh.Trimesh``, a mesh file or a built-in object name (see ``load_mesh``).
        pred: tracked trajectory ``(t_us (N,) int64, poses (N, 7))``.
        times_us: ``(K,)`` non-decreasing frame times, microseconds (EROS as in :func:`iter_eros`).
        gt: optional ground-truth trajectory, same layout as ``pred``.
        kernel_size, decay: EROS parameters.
        depth_jump, thickness: contour options (see :func:`contour_mask`).
        legend: write the time and the colour key at the top-left.
        brightness: EROS grey scale (see :func:`overlay`).

    Shape: yields ``(H, W, 3)`` uint8 images.
    """
    from torchevtrack.mesh import load_mesh
    from torchevtrack.render import Renderer

    times = _check_times(times_us)
    named = [("tracked", PRED_COLOUR, _check_trajectory(pred, "pred"))]
    if gt is not None:
        named.insert(0, ("ground truth", GT_COLOUR, _check_trajectory(gt, "gt")))  # drawn first, below
    poses = [_poses_at(traj, times) for _, _, traj in named]
    with Renderer(load_mesh(mesh), camera) as renderer:
        surfaces = iter_eros(events, camera, times, kernel_size=kernel_size, decay=decay)
        for k, (t, surface) in enumerate(zip(times.tolist(), surfaces)):
            have = [i for i in range(len(named)) if poses[i][k] is not None]
            depth = renderer.render(torch.stack([poses[i][k] for i in have]), shaded=False).depth if have else []
            contours = [(contour_mask(d, thickness=thickness, depth_jump=depth_jump), named[i][1])
                        for i, d in zip(have, depth)]
            key = None
            if legend:
                key = [(f"t = {t / 1e6:.3f} s", None)]
                key += [(name if i in have else f"{name}: no pose", colour)
                        for i, (name, colour, _) in enumerate(named)][::-1]
            yield overlay(surface, contours, legend=key, brightness=brightness)


def overlay_frames(events: EventStream, camera: Camera, mesh, pred, times_us, gt=None,
                   **kwargs) -> list[np.ndarray]:
    """List of the images of :func:`iter_overlay_frames` (same arguments)."""
    return list(iter_overlay_frames(events, camera, mesh, pred, times_us, gt, **kwargs))


def _has_ffmpeg() -> bool:
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def save_video(frames: Iterable, path: str | Path, fps: float = 30.0) -> Path:
    """Write RGB frames as an animation; the format comes from the extension.

    ``.gif``: imageio's pillow writer (frames are palette-quantised; identical consecutive frames are
    merged into one longer frame). ``.mp4``: H.264 through imageio-ffmpeg; if that package is not
    installed, a GIF is written next to it (``path`` with ``.gif``) with a warning.

    Args:
        frames: iterable of ``(H, W, 3)`` uint8 images of one size (consumed as they come).
        path: output file, ``.gif`` or ``.mp4``.
        fps: frames per second (> 0).

    Returns:
        The path actually written.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in VIDEO_EXTENSIONS:
        raise ValueError(f"unsupported video extension {path.suffix!r} for {path}: use one of {VIDEO_EXTENSIONS}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if ext == ".mp4" and not _has_ffmpeg():
        path = path.with_suffix(".gif")
        ext = ".gif"
        warnings.warn(f"imageio-ffmpeg is not installed: writing a GIF instead, {path}", stacklevel=2)

    shape = None

    def checked(i: int, f) -> np.ndarray:
        nonlocal shape
        a = _numpy(f, f"frames[{i}]")
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"frames[{i}] must be an (H, W, 3) uint8 image, got {a.dtype} {a.shape}")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise ValueError(f"frames[{i}] has shape {a.shape}, the first frame {shape}")
        return a

    import imageio.v2 as iio2
    import imageio.v3 as iio

    from torchevtrack.io.atomic import replacing

    n = 0
    out = replacing(path)  # an existing video stays as it was if a frame fails
    try:
        if ext == ".gif":
            with iio.imopen(out.tmp, "w", plugin="pillow", extension=".gif") as writer:
                for n, f in enumerate(frames, start=1):
                    writer.write(checked(n - 1, f), duration=1000.0 / fps, loop=0)
        else:
            with iio2.get_writer(out.tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                 macro_block_size=1) as writer:
                for n, f in enumerate(frames, start=1):
                    writer.append_data(checked(n - 1, f))
    except BaseException:
        out.discard()
        raise
    if n == 0:
        out.discard()
        raise ValueError("no frames to write")
    out.commit()
    return path


# -- error plots ----------------------------------------------------------------------------------
def _series(values, name: str) -> np.ndarray:
    a = np.asarray(_numpy(values, name) if isinstance(values, torch.Tensor) else values, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    return a


def plot_errors_multi(methods: Mapping[str, tuple], path: str | Path, title: str | None = None) -> Path:
    """Error-against-time PNG for several methods on the same two stacked axes (translation in cm
    on top, rotation in degrees below), one line per method, rendered with matplotlib's Agg canvas.

    Args:
        methods: ``{name: (t_s (N,), te_cm (N,), re_deg (N,))}``; time in seconds.
        path: output ``.png``.
        title: figure title.

    Returns the written path.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"plot path must end with .png, got {path}")
    if not isinstance(methods, Mapping) or not methods:
        raise ValueError("methods must be a non-empty mapping name -> (t_s, te_cm, re_deg)")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 5.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax_t, ax_r = fig.subplots(2, 1, sharex=True)
    for name, series in methods.items():
        if not isinstance(series, (tuple, list)) or len(series) != 3:
            raise ValueError(f"methods[{name!r}] must be a (t_s, te_cm, re_deg) triple")
        t, te, re = (_series(v, f"methods[{name!r}][{i}]") for i, v in enumerate(series))
        if not t.shape == te.shape == re.shape:
            raise ValueError(f"methods[{name!r}]: t_s, te_cm, re_deg lengths differ: {t.shape}, {te.shape}, {re.shape}")
        label = str(name) or None
        ax_t.plot(t, te, lw=1.0, label=label)
        ax_r.plot(t, re, lw=1.0, label=label)
    ax_t.set_ylabel("translation error [cm]")
    ax_r.set_ylabel("rotation error [deg]")
    ax_r.set_xlabel("time [s]")
    for ax in (ax_t, ax_r):
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.3)
    if any(str(k) for k in methods):
        ax_t.legend(loc="upper left", fontsize="small")
    if title:
        fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    from torchevtrack.io.atomic import replacing

    with replacing(path) as tmp:
        fig.savefig(tmp)
    return path


def plot_errors(t_s, te_cm, re_deg, path: str | Path, title: str | None = None) -> Path:
    """Error-against-time PNG of one method (see :func:`plot_errors_multi`).

    Shape: ``t_s, te_cm, re_deg`` ``(N,)``: seconds, centimetres, degrees.
    """
    return plot_errors_multi({"": (t_s, te_cm, re_deg)}, path, title)
