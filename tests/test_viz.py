"""Tests for torchevtrack.viz and the ``viz`` command, against brute-force loops and read-back files."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy import ndimage

from torchevtrack import viz
from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.events import EventStream
from torchevtrack.geometry import quat_exp, quat_mul
from torchevtrack.io.events_h5 import write_events_h5
from torchevtrack.io.poses import write_tum
from torchevtrack.mesh import load_mesh
from torchevtrack.render import Renderer
from torchevtrack.stages.eros import EROS

CAM = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
GREEN, MAGENTA = np.array(viz.PRED_COLOUR), np.array(viz.GT_COLOUR)


def box_pose(tx: float = 0.0, angle: float = 0.5) -> torch.Tensor:
    q = quat_exp(torch.tensor([0.4, 0.7, 0.2], dtype=torch.float64) * angle)
    return torch.cat((torch.tensor([tx, 0.005, 0.6], dtype=torch.float64), q))


def contour_oracle(depth: np.ndarray, thickness: int, depth_jump: float | None) -> np.ndarray:
    """The contour definition, pixel by pixel with in-image 4-neighbours."""
    H, W = depth.shape
    out = np.zeros((H, W), bool)
    for v in range(H):
        for u in range(W):
            d = depth[v, u]
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                if not (0 <= v + dv < H and 0 <= u + du < W):
                    continue
                n = depth[v + dv, u + du]
                if d > 0 and n == 0:
                    out[v, u] = True
                if thickness == 2 and d == 0 and n > 0:
                    out[v, u] = True
                if depth_jump is not None and d > 0 and n > 0:
                    if n - d > depth_jump or (thickness == 2 and d - n > depth_jump):
                        out[v, u] = True
    return out


@pytest.fixture(scope="module")
def box_depth() -> np.ndarray:
    with Renderer(load_mesh("box"), CAM) as r:
        return r.render(box_pose(), shaded=False).depth[0].numpy()


# -- contour_mask ---------------------------------------------------------------------------------
@pytest.mark.parametrize("thickness", [1, 2])
def test_contour_of_rendered_box_is_closed_thin_ring(box_depth, thickness):
    depth = box_depth
    fg = depth > 0
    assert 150 < fg.sum() < depth.size // 2 and not fg[0].any() and not fg[-1].any()  # fully inside
    ring = viz.contour_mask(torch.from_numpy(depth), thickness=thickness)
    assert np.array_equal(ring, contour_oracle(depth, thickness, None))
    # thin: every ring pixel sees both object and background within its 3 x 3 neighbourhood
    H, W = depth.shape
    for v, u in zip(*np.nonzero(ring)):
        win = depth[max(v - 1, 0): v + 2, max(u - 1, 0): u + 2]
        assert (win > 0).any() and (win == 0).any(), (v, u)
    # one connected ring (8-connectivity) ...
    _, n_parts = ndimage.label(ring, structure=np.ones((3, 3)))
    assert n_parts == 1
    # ... that separates the object's inside from the outside (4-conn. for 1 px, 8-conn. for 2 px)
    structure = ndimage.generate_binary_structure(2, 1 if thickness == 1 else 2)
    labels, _ = ndimage.label(~ring, structure=structure)
    inside = fg & ~ring
    assert inside.sum() > 20
    assert labels[0, 0] not in set(np.unique(labels[inside]).tolist())
    if thickness == 1:
        assert not ring[~fg].any()  # object side only
    else:
        assert ring[~fg].any() and ring[fg].any()


def test_contour_internal_depth_edges():
    depth = np.zeros((9, 10), np.float32)
    depth[1:8, 1:9] = 1.0  # far plane
    depth[3:6, 3:6] = 0.5  # near square in front of it
    depth[6, 7] = 0.99  # a 1 cm step: below the threshold
    for thickness in (1, 2):
        got = viz.contour_mask(depth, thickness=thickness, depth_jump=0.1)
        assert np.array_equal(got, contour_oracle(depth, thickness, 0.1))
    near_side = viz.contour_mask(depth, thickness=1, depth_jump=0.1) & ~viz.contour_mask(depth, thickness=1)
    expected = np.zeros_like(near_side)
    expected[3:6, 3:6] = True
    expected[4, 4] = False  # the centre of the 3 x 3 square has only near neighbours
    assert np.array_equal(near_side, expected)


def test_contour_rejects_bad_input():
    with pytest.raises(ValueError, match="depth"):
        viz.contour_mask(np.zeros((2, 3, 4), np.float32))
    with pytest.raises(ValueError, match="depth"):
        viz.contour_mask(np.full((3, 3), -1.0))
    with pytest.raises(ValueError, match="thickness"):
        viz.contour_mask(np.zeros((3, 3)), thickness=3)
    with pytest.raises(TypeError, match="depth"):
        viz.contour_mask([[0.0]])


# -- overlay --------------------------------------------------------------------------------------
def test_overlay_colours_at_known_pixels():
    eros = np.zeros((6, 8), np.float32)
    eros[0, 0], eros[5, 7], eros[2, 3] = 1.0, 0.5, 0.25
    a = np.zeros((6, 8), bool)
    a[1, 1] = a[2, 2] = True
    b = np.zeros((6, 8), bool)
    b[2, 2] = b[3, 3] = True
    img = viz.overlay(torch.from_numpy(eros), [(a, (255, 0, 255)), (b, (0, 255, 0))], brightness=0.8)
    assert img.dtype == np.uint8 and img.shape == (6, 8, 3)
    assert img[1, 1].tolist() == [255, 0, 255]
    assert img[2, 2].tolist() == [0, 255, 0]  # later contour on top
    assert img[3, 3].tolist() == [0, 255, 0]
    assert img[0, 0].tolist() == [204] * 3  # round(255 * 0.8 * 1.0)
    assert img[5, 7].tolist() == [102] * 3
    assert img[2, 3].tolist() == [51] * 3
    assert img[4, 4].tolist() == [0, 0, 0]


def test_overlay_legend_is_top_left_and_coloured():
    eros = np.full((60, 120), 0.5, np.float32)
    plain = viz.overlay(eros)
    img = viz.overlay(eros, legend=[("t = 1 s", None), ("tracked", (0, 255, 0)), ("gt", (255, 0, 255))])
    changed = (img != plain).any(axis=-1)
    rows, cols = np.nonzero(changed)
    assert rows.max() < 50 and cols.max() < 80 and changed.sum() > 50
    assert (img[changed] == [0, 255, 0]).all(axis=-1).any()
    assert (img[changed] == [255, 0, 255]).all(axis=-1).any()


def test_overlay_rejects_bad_input():
    with pytest.raises(ValueError, match="mask"):
        viz.overlay(np.zeros((4, 4)), [(np.zeros((4, 5), bool), (0, 255, 0))])
    with pytest.raises(ValueError, match="colour"):
        viz.overlay(np.zeros((4, 4)), [(np.zeros((4, 4), bool), (0, 300, 0))])
    with pytest.raises(ValueError, match="eros"):
        viz.overlay(np.zeros((4, 4, 3)))


# -- EROS at sample times -------------------------------------------------------------------------
@pytest.mark.parametrize("chunk", [7, 100_000])
def test_eros_frames_equal_sequential_eros(monkeypatch, chunk):
    monkeypatch.setattr(viz, "_EROS_CHUNK", chunk)
    g = torch.Generator().manual_seed(3)
    cam = Camera(9, 7, 10.0, 10.0, 4.0, 3.0)
    n = 300
    t = torch.sort(torch.randint(100, 5_000, (n,), generator=g)).values
    ev = EventStream.from_arrays(torch.randint(0, 9, (n,), generator=g), torch.randint(0, 7, (n,), generator=g),
                                 t, torch.randint(0, 2, (n,), generator=g), width=9, height=7)
    times = torch.tensor([0, 100, int(t[40]), int(t[40]), 2_500, int(t[-1]), 9_000])
    got = viz.eros_frames(ev, cam, times, kernel_size=3, decay=0.4)
    # oracle: one event at a time, snapshot before the first event at or after each sample time
    ref = EROS(7, 9, kernel_size=3, decay=0.4)
    expected, i = [], 0
    for ts in times.tolist():
        while i < n and int(t[i]) < ts:
            ref(ev.x[i:i + 1], ev.y[i:i + 1])
            i += 1
        expected.append(ref.surface[0].clone())
    assert got.shape == (7, 7, 9)
    torch.testing.assert_close(got, torch.stack(expected), atol=1e-6, rtol=0)
    assert got[0].abs().max() == 0 and got[-1].max() == 1.0


def test_eros_frames_rejects_unsorted_times():
    ev = EventStream.from_arrays([1], [1], [5], [1])
    with pytest.raises(ValueError, match="non-decreasing"):
        viz.eros_frames(ev, CAM, torch.tensor([10, 5]))
    with pytest.raises(TypeError, match="integer"):
        viz.eros_frames(ev, CAM, torch.tensor([0.5]))


# -- overlay frames -------------------------------------------------------------------------------
def test_overlay_frames_draw_gt_and_pred_and_skip_outside_range():
    gt_t = torch.tensor([0, 10_000])
    gt = (gt_t, torch.stack([box_pose(-0.01), box_pose(0.01)]))
    pred = (torch.tensor([5_000, 10_000]), torch.stack([box_pose(0.02), box_pose(0.03)]))
    ev = EventStream.from_arrays([10, 20], [10, 20], [1_000, 2_000], [1, 0])
    frames = viz.overlay_frames(ev, CAM, "box", pred, torch.tensor([2_000, 7_500]), gt, legend=False)
    assert len(frames) == 2 and frames[0].shape == (48, 64, 3)
    green = [(f == GREEN).all(-1) for f in frames]
    magenta = [(f == MAGENTA).all(-1) for f in frames]
    assert not green[0].any() and magenta[0].sum() > 30  # t = 2 ms is before the first tracked pose
    assert green[1].sum() > 30 and magenta[1].sum() > 30
    # the tracked box is further right than the ground truth
    assert np.nonzero(green[1])[1].mean() > np.nonzero(magenta[1])[1].mean() + 3


# -- video and plots ------------------------------------------------------------------------------
def _frames(n: int) -> list[np.ndarray]:
    out = []
    for k in range(n):
        f = np.zeros((12, 16, 3), np.uint8)
        f[:, k] = (255, 0, 255)
        f[k % 12, :] = (0, 255, 0)
        out.append(f)
    return out


def test_save_video_gif_reads_back(tmp_path):
    frames = _frames(5)
    path = viz.save_video(iter(frames), tmp_path / "a.gif", fps=20)
    assert path == tmp_path / "a.gif"
    back = iio.imread(path, index=None)
    assert back.shape == (5, 12, 16, 3)
    np.testing.assert_array_equal(back, np.stack(frames))
    assert iio.immeta(path)["duration"] == 50


def test_save_video_errors_and_mp4_fallback(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="extension"):
        viz.save_video(_frames(2), tmp_path / "a.avi")
    with pytest.raises(ValueError, match="no frames"):
        viz.save_video([], tmp_path / "b.gif")
    assert not (tmp_path / "b.gif").exists()
    with pytest.raises(ValueError, match="shape"):
        viz.save_video([np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5, 3), np.uint8)], tmp_path / "c.gif")
    monkeypatch.setattr(viz, "_has_ffmpeg", lambda: False)
    with pytest.warns(UserWarning, match="imageio-ffmpeg"):
        path = viz.save_video(_frames(3), tmp_path / "d.mp4", fps=10)
    assert path == tmp_path / "d.gif" and iio.imread(path, index=None).shape == (3, 12, 16, 3)


def test_save_video_mp4_with_ffmpeg(tmp_path):
    pytest.importorskip("imageio_ffmpeg")  # optional encoder; the GIF path above is the core one
    path = viz.save_video(_frames(4), tmp_path / "a.mp4", fps=10)
    assert path.suffix == ".mp4" and iio.imread(path, index=None, plugin="FFMPEG").shape[0] == 4


def test_plot_errors_png(tmp_path):
    t = np.linspace(0, 2, 50)
    one = viz.plot_errors(t, np.abs(np.sin(t)), torch.from_numpy(t * 3), tmp_path / "e.png", title="run")
    img = iio.imread(one)
    assert img.shape[:2] == (500, 800) and img.reshape(-1, img.shape[-1]).std(0).max() > 10
    two = viz.plot_errors_multi({"a": (t, t, t), "b": (t, 2 * t, t / 2)}, tmp_path / "f.png")
    assert iio.imread(two).shape[:2] == (500, 800)
    with pytest.raises(ValueError, match="lengths"):
        viz.plot_errors(t, t[:3], t, tmp_path / "g.png")
    with pytest.raises(ValueError, match="png"):
        viz.plot_errors(t, t, t, tmp_path / "g.jpg")


# -- CLI ------------------------------------------------------------------------------------------
@pytest.fixture
def seq_dir(tmp_path):
    d = tmp_path / "seq"
    d.mkdir()
    CAM.save(d / "camera.json")
    gt_t = torch.arange(0, 100_001, 2_000)
    gt_p = torch.stack([box_pose(-0.02 + 0.04 * k / 50, 0.5 + 0.2 * k / 50) for k in range(51)])
    write_tum(d / "gt_poses.txt", gt_t, gt_p)
    load_mesh("box").export(d / "mesh.ply")
    g = torch.Generator().manual_seed(0)
    n = 2_000
    ev = EventStream.from_arrays(torch.randint(0, 64, (n,), generator=g), torch.randint(0, 48, (n,), generator=g),
                                 torch.sort(torch.randint(0, 100_000, (n,), generator=g)).values,
                                 torch.randint(0, 2, (n,), generator=g), width=64, height=48)
    write_events_h5(d / "events.h5", ev, width=64, height=48)
    (d / "meta.json").write_text(json.dumps({"object": "box"}))
    # a tracked trajectory 1.5 cm and 5 degrees off the ground truth
    rot = quat_exp(torch.tensor([0.0, 0.0, math.radians(5.0)], dtype=torch.float64)).expand(51, 4)
    off = torch.cat((gt_p[:, :3] + torch.tensor([0.015, 0.0, 0.0], dtype=torch.float64),
                     quat_mul(rot, gt_p[:, 3:])), dim=-1)
    write_tum(tmp_path / "pred.txt", gt_t, off)
    return d


def test_cli_viz_gif_and_png(seq_dir, tmp_path):
    pred = str(tmp_path / "pred.txt")
    out = tmp_path / "o" / "v.gif"
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(out), "--every-ms", "20",
                 "--duration", "0.08", "--fps", "10", "--quiet"]) == 0
    back = iio.imread(out, index=None)
    assert back.shape == (5, 48, 64, 3)  # 0, 20, ..., 80 ms
    png = tmp_path / "f.png"
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(png), "--time", "0.05", "--no-legend",
                 "--quiet"]) == 0
    img = iio.imread(png)
    assert img.shape == (48, 64, 3)
    assert (img == GREEN).all(-1).sum() > 30 and (img == MAGENTA).all(-1).sum() > 30
    no_gt = tmp_path / "n.png"
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(no_gt), "--no-gt", "--no-legend",
                 "--quiet"]) == 0
    img = iio.imread(no_gt)
    assert (img == GREEN).all(-1).sum() > 30 and not (img == MAGENTA).all(-1).any()


def test_cli_viz_real_recording_without_gt(seq_dir, tmp_path, capsys):
    (seq_dir / "gt_poses.txt").unlink()
    (seq_dir / "mesh.ply").unlink()
    pred = str(tmp_path / "pred.txt")
    png = tmp_path / "r.png"
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(png), "--quiet"]) == 2
    assert "--mesh" in capsys.readouterr().err
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(png), "--mesh", "box", "--no-legend",
                 "--quiet"]) == 0
    img = iio.imread(png)
    assert (img == GREEN).all(-1).sum() > 30 and not (img == MAGENTA).all(-1).any()
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(tmp_path / "x.jpg"), "--mesh", "box"]) == 2
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(png), "--mesh", "box", "--time", "5"]) == 2


def test_cli_viz_reads_events_in_another_format(seq_dir, tmp_path, capsys):
    """``--events`` in text format draws the frame the directory's events.h5 draws; without either, one line."""
    from torchevtrack.io.events_h5 import read_events_h5
    from torchevtrack.io.formats import write_events

    pred = str(tmp_path / "pred.txt")
    write_events(tmp_path / "ev.txt", read_events_h5(seq_dir / "events.h5"), width=64, height=48)
    frames = {}
    for name, extra in (("h5", []), ("txt", ["--events", str(tmp_path / "ev.txt")])):
        frames[name] = tmp_path / f"{name}.png"
        assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(frames[name]), "--time", "0.05",
                     "--quiet"] + extra) == 0
    assert np.array_equal(iio.imread(frames["h5"]), iio.imread(frames["txt"]))
    (seq_dir / "events.h5").unlink()
    capsys.readouterr()
    assert main(["viz", str(seq_dir), "--poses", pred, "--out", str(tmp_path / "x.png"), "--quiet"]) == 2
    assert "has no events.h5: give the event file with --events" in capsys.readouterr().err
