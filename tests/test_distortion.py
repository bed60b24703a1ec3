"""Lens distortion: model against a direct numpy transcription of OpenCV's formula, inversion against
scipy root finding and round trips, event undistortion against geometry (straight lines stay straight)."""

import json

import numpy as np
import pytest
import scipy.optimize
import torch

from torchevtrack.camera import Camera
from torchevtrack.distortion import (
    Undistorter,
    as_coeffs,
    distort_points,
    nearest_table,
    remap_pixels,
    undistort_events,
    undistort_pixels,
    undistort_points,
    undistortion_map,
)
from torchevtrack.events import EventStream

# YCB-Ev-like: Prophesee 1280x720 sensor with strong barrel distortion.
CAM = Camera(1280, 720, 900.0, 900.0, 639.5, 359.5)
STRONG = (-0.3, 0.1, 1e-3, -5e-4, 0.0)
SMALL = Camera(160, 120, 110.0, 112.0, 80.2, 58.7)


def opencv_distort_np(x, y, k1, k2, p1, p2, k3):
    """OpenCV's projectPoints distortion, written out term by term."""
    r2 = x ** 2 + y ** 2
    radial = 1.0 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x ** 2)
    yd = y * radial + p1 * (r2 + 2.0 * y ** 2) + 2.0 * p2 * x * y
    return xd, yd


def to_pixels(xy, cam):
    return torch.stack((xy[..., 0] * cam.fx + cam.cx, xy[..., 1] * cam.fy + cam.cy), -1)


def to_normalised(uv, cam):
    return torch.stack(((uv[..., 0] - cam.cx) / cam.fx, (uv[..., 1] - cam.cy) / cam.fy), -1)


@pytest.mark.parametrize("coeffs", [STRONG, (0.12, -0.05, -2e-3, 1e-3, 0.01), (0.0, 0.0, 0.0, 0.0, 0.0)])
def test_distort_matches_the_opencv_formula(coeffs):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.9, 0.9, (500, 2))
    got = distort_points(torch.from_numpy(xy), coeffs).numpy()
    xd, yd = opencv_distort_np(xy[:, 0], xy[:, 1], *coeffs)
    np.testing.assert_allclose(got, np.stack((xd, yd), 1), rtol=0, atol=1e-14)


def test_four_coefficients_mean_k3_zero():
    xy = torch.tensor([[0.3, -0.4]], dtype=torch.float64)
    torch.testing.assert_close(distort_points(xy, STRONG[:4]), distort_points(xy, STRONG))
    assert as_coeffs(STRONG[:4]).tolist() == list(STRONG)


def test_undistort_matches_scipy_root_finding():
    rng = np.random.default_rng(1)
    uv = np.stack((rng.uniform(0, CAM.width - 1, 60), rng.uniform(0, CAM.height - 1, 60)), 1)
    got = undistort_points(torch.from_numpy(uv), CAM, STRONG).numpy()
    for (u, v), g in zip(uv, got):
        xd, yd = (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy

        def residual(p):
            return np.array(opencv_distort_np(p[0], p[1], *STRONG)) - (xd, yd)

        sol = scipy.optimize.fsolve(residual, x0=(xd, yd), xtol=1e-12)
        np.testing.assert_allclose(g, (sol[0] * CAM.fx + CAM.cx, sol[1] * CAM.fy + CAM.cy), rtol=0, atol=1e-6)


def test_round_trips_over_the_whole_sensor():
    grid = CAM.pixel_grid(torch.float64)
    und = undistort_points(grid, CAM, STRONG)
    assert torch.isfinite(und).all()
    # Strong distortion: the corners move by tens of pixels.
    assert (und - grid).norm(dim=-1).max() > 50
    back = to_pixels(distort_points(to_normalised(und, CAM), STRONG), CAM)
    assert (back - grid).abs().max() < 1e-6
    # The other direction: ideal pinhole pixels -> sensor -> ideal.
    ideal = grid[::7, ::7]
    sensor = to_pixels(distort_points(to_normalised(ideal, CAM), STRONG), CAM)
    assert (undistort_points(sensor, CAM, STRONG) - ideal).abs().max() < 1e-6


def test_points_without_inverse_are_nan():
    # k1 = -0.6: r (1 - 0.6 r^2) peaks at r_d = 0.544; a sensor point farther out has no preimage.
    cam = Camera(100, 100, 100.0, 100.0, 0.0, 0.0)
    out = undistort_points(torch.tensor([[70.0, 0.0], [30.0, 10.0]], dtype=torch.float64), cam, (-0.6, 0, 0, 0, 0))
    assert torch.isnan(out[0]).all() and torch.isfinite(out[1]).all()


def test_map_is_the_pointwise_undistortion():
    lut = undistortion_map(SMALL, STRONG)
    assert lut.shape == (SMALL.height, SMALL.width, 2)
    uv = torch.tensor([[5.0, 7.0], [150.0, 100.0]], dtype=torch.float64)
    torch.testing.assert_close(lut[[7, 100], [5, 150]], undistort_points(uv, SMALL, STRONG))


def _line_events(cam, coeffs, a, b, n):
    """Events along the ideal (pinhole) line v = a u + b, as seen by the distorting sensor."""
    u = torch.linspace(0, cam.width - 1, n, dtype=torch.float64)
    ideal = torch.stack((u, a * u + b), -1)
    sensor = to_pixels(distort_points(to_normalised(ideal, cam), coeffs), cam).round()
    inside = (sensor[:, 0] >= 0) & (sensor[:, 0] < cam.width) & (sensor[:, 1] >= 0) & (sensor[:, 1] < cam.height)
    sensor = sensor[inside].long()
    t = torch.arange(len(sensor), dtype=torch.int64) * 10
    return EventStream.from_arrays(sensor[:, 0], sensor[:, 1], t, torch.ones(len(sensor), dtype=torch.int64))


def _line_residuals(x, y):
    """Perpendicular residuals of the total-least-squares line through the points."""
    pts = np.stack((x, y), 1).astype(np.float64)
    pts -= pts.mean(0)
    normal = np.linalg.svd(pts, full_matrices=False)[2][-1]
    return pts @ normal


def test_undistorted_line_is_straight():
    ev = _line_events(CAM, STRONG, a=0.1, b=60.0, n=4000)  # a line near the top edge: strongly bent
    raw = _line_residuals(ev.x.numpy(), ev.y.numpy())
    assert np.abs(raw).max() > 10  # the sensor sees a curve
    out = undistort_events(ev, CAM, STRONG)
    assert len(out) > 0.9 * len(ev)
    res = _line_residuals(out.x.numpy(), out.y.numpy())
    assert np.sqrt(np.mean(res ** 2)) < 0.5 and np.abs(res).max() < 1.5  # two roundings, magnified at the edge
    # The line comes back where it was drawn, not just straight.
    u = out.x.double().numpy()
    assert np.abs(out.y.double().numpy() - (0.1 * u + 60.0)).max() < 1.5


def test_events_keep_time_and_polarity_and_drops_are_counted():
    rng = np.random.default_rng(2)
    n = 5000
    x, y = rng.integers(0, SMALL.width, n), rng.integers(0, SMALL.height, n)
    t, p = np.sort(rng.integers(0, 10**6, n)), rng.integers(0, 2, n)
    ev = EventStream.from_arrays(x, y, t, p)
    out = undistort_events(ev, SMALL, STRONG)
    # Independent check per event: undistort the event's pixel on its own and round.
    exact = undistort_points(torch.from_numpy(np.stack((x, y), 1)).double(), SMALL, STRONG).round()
    inside = ((exact[:, 0] >= 0) & (exact[:, 0] < SMALL.width) & (exact[:, 1] >= 0)
              & (exact[:, 1] < SMALL.height))
    assert 0 < n - len(out) == int((~inside).sum())  # barrel distortion pushes the corners out
    assert torch.equal(out.x.long(), exact[inside, 0].long()) and torch.equal(out.y.long(), exact[inside, 1].long())
    assert torch.equal(out.t, ev.t[inside]) and torch.equal(out.p, ev.p[inside])
    assert out.x.dtype == torch.int16 and out.t.dtype == torch.int64
    out.validate(SMALL.width, SMALL.height)


def test_undistorter_on_chunks_equals_the_whole_stream():
    rng = np.random.default_rng(3)
    n = 3000
    ev = EventStream.from_arrays(rng.integers(0, SMALL.width, n), rng.integers(0, SMALL.height, n),
                                 np.arange(n), rng.integers(0, 2, n))
    whole = undistort_events(ev, SMALL, STRONG)
    und = Undistorter(SMALL, STRONG)
    parts = [und(ev[i:i + 700]) for i in range(0, n, 700)]
    merged = EventStream.concat(parts)
    for f in "xytp":
        assert torch.equal(getattr(merged, f), getattr(whole, f))
    assert int(und.dropped) == n - len(whole)
    assert und(EventStream.empty()).t.numel() == 0


def test_fast_table_equals_float_rounding():
    lut = undistortion_map(SMALL, STRONG).float()
    y, x = torch.meshgrid(torch.arange(SMALL.height), torch.arange(SMALL.width), indexing="ij")
    x, y = x.flatten().short(), y.flatten().short()
    a = remap_pixels(x, y, nearest_table(lut), SMALL.width)
    b = undistort_pixels(x, y, lut, "nearest")
    for u, v in zip(a, b):
        assert torch.equal(u, v)


def test_random_rounding_is_unbiased():
    lut = torch.tensor([[[2.3, 1.75]]]).expand(3, 4, 2).contiguous()
    x = torch.zeros(20000, dtype=torch.long)
    g = torch.Generator().manual_seed(0)
    nx, ny, keep = undistort_pixels(x, x.clone(), lut, "random", g)
    assert keep.all()
    assert set(nx.tolist()) == {2, 3} and set(ny.tolist()) == {1, 2}
    assert abs(nx.double().mean() - 2.3) < 0.02 and abs(ny.double().mean() - 1.75) < 0.02


def test_camera_carries_distortion_through_json(tmp_path):
    cam = Camera(64, 48, 50.0, 51.0, 31.5, 23.5, distortion=STRONG[:4])
    assert cam.distortion == STRONG
    cam.save(tmp_path / "cam.json")
    assert json.loads((tmp_path / "cam.json").read_text())["distortion"] == list(STRONG)
    assert Camera.load(tmp_path / "cam.json") == cam
    assert cam.crop(2, 3, 10, 10).distortion == STRONG and cam.scale(0.5).distortion == STRONG
    # Coefficients default to the camera's.
    torch.testing.assert_close(undistortion_map(cam), undistortion_map(cam, STRONG))
    # A pinhole camera.json (no distortion key) still loads, and pinhole cameras write no such key.
    (tmp_path / "old.json").write_text(json.dumps({"width": 64, "height": 48, "fx": 50, "fy": 51, "cx": 31.5,
                                                   "cy": 23.5}))
    old = Camera.load(tmp_path / "old.json")
    assert old.distortion is None and "distortion" not in old.to_dict()


@pytest.mark.parametrize("kwargs, err, match", [
    ({"coeffs": (0.1, 0.2, 0.3)}, ValueError, "k1, k2, p1, p2"),
    ({"coeffs": (0.1, float("nan"), 0, 0)}, ValueError, "finite"),
    ({"coeffs": None}, ValueError, "no distortion coefficients"),
    ({"coeffs": STRONG, "iterations": 0}, ValueError, "iterations"),
])
def test_bad_arguments(kwargs, err, match):
    with pytest.raises(err, match=match):
        undistort_points(torch.zeros(1, 2), SMALL, **kwargs)


def test_bad_events_and_options():
    with pytest.raises(ValueError, match="distortion must be"):
        Camera(4, 4, 1.0, 1.0, 2.0, 2.0, distortion=(0.1,))
    with pytest.raises(ValueError, match="rounding"):
        Undistorter(SMALL, STRONG, rounding="floor")
    lut = undistortion_map(SMALL, STRONG)
    with pytest.raises(ValueError, match="inside the 160x120 sensor"):
        undistort_pixels(torch.tensor([160]), torch.tensor([0]), lut)
    with pytest.raises(TypeError, match="integer"):
        undistort_pixels(torch.tensor([1.0]), torch.tensor([0]), lut)
