"""Hard inputs for the tracker and its event stages: long silences, gaps, bursts, objects leaving the
view, bad poses and meshes, and property-based checks of EROS and TripletFlow on arbitrary packets."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.metrics import pose_errors
from torchevtrack.stages.eros import EROS
from torchevtrack.stages.flow import NEVER, TripletFlow, _prepare, sae_update, triplet_samples
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

SMALL = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
POSE0 = torch.tensor([0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
EMPTY = torch.zeros(0, dtype=torch.long)


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.06, seed=3, camera=CAM, progress=False)


def _assert_valid_poses(poses, atol=1e-9):
    poses = poses.reshape(-1, 7)
    assert torch.isfinite(poses).all()
    torch.testing.assert_close(poses[:, 3:].norm(dim=-1), torch.ones(len(poses), dtype=torch.float64),
                               atol=atol, rtol=0)
    assert (poses[:, 2] > 0).all()


def _noise(t0, n, g, cam=SMALL, period=2000):
    x = torch.randint(0, cam.width, (n,), generator=g)
    y = torch.randint(0, cam.height, (n,), generator=g)
    t = torch.sort(torch.randint(t0, t0 + period, (n,), generator=g)).values
    return x, y, t, torch.randint(0, 2, (n,), generator=g)


def _window(ev: EventStream, t0, t1, shift=0):
    w = ev.slice_time(t0, t1)
    return w.x.long(), w.y.long(), w.t + shift, w.p.long()


# -- silence and gaps --------------------------------------------------------------------------------
def test_long_run_of_empty_windows_keeps_the_pose():
    tracker = EventPoseTracker(SMALL, "can")
    tracker.reset(POSE0)
    poses = torch.stack([tracker(EMPTY, EMPTY, EMPTY, EMPTY) for _ in range(100)])  # 0.2 s of silence
    tracker.close()
    _assert_valid_poses(poses)
    torch.testing.assert_close(poses[-1, 0], POSE0, atol=1e-6, rtol=0)
    q = tracker.quality
    assert int(q.events[0]) == 0 and int(q.flow_vectors[0]) == 0 and not bool(q.rejected[0])


def test_gap_without_events_then_events_again(seq):
    """40 ms of motion, 0.15 s of silence (the object waits), the rest of the motion: tracking resumes."""
    gap_updates, cut = 75, 40_000  # the gap is longer than the flow's dt_max (50 ms)
    gap = gap_updates * 2000
    tracker = EventPoseTracker(CAM, seq.mesh)
    tracker.reset(seq.gt_poses[0])
    poses, flows = [], []
    for k in range(cut // 2000):
        poses.append(tracker(*_window(seq.events, 2000 * k, 2000 * (k + 1))))
    for _ in range(gap_updates):
        poses.append(tracker(EMPTY, EMPTY, EMPTY, EMPTY))
    t_end = int(seq.gt_t_us[-1])
    for k in range(cut // 2000, t_end // 2000):
        poses.append(tracker(*_window(seq.events, 2000 * k, 2000 * (k + 1), shift=gap)))
        flows.append(int(tracker.quality.flow_vectors[0]))
    tracker.close()
    poses = torch.stack(poses)[:, 0]
    _assert_valid_poses(poses)
    # The silence does not move the estimate (the velocity filter decays to rest) ...
    drift = pose_errors(poses[None, cut // 2000 + gap_updates - 1], poses[None, cut // 2000 - 1])
    assert float(drift["te"][0]) < 0.005
    # ... the flow comes back once the time surface has fresh events, and tracking goes on.
    assert max(flows[5:]) >= 3
    err = pose_errors(poses[-1:], seq.gt_poses[t_end // 2000][None])
    assert float(err["te"][0]) < 0.03 and float(err["re"][0]) < 0.2


def test_absolute_time_offset_changes_nothing(seq):
    """Timestamps near 1.7e15 us (Unix time) give the same poses as timestamps from 0."""
    offset = 1_700_000_000_000_000
    runs = []
    for shift in (0, offset):
        tracker = EventPoseTracker(CAM, seq.mesh, TrackerConfig().replace(**ABLATIONS["no_ukf"]))
        tracker.reset(seq.gt_poses[0])
        runs.append(torch.stack([tracker(*_window(seq.events, 2000 * k, 2000 * (k + 1), shift))
                                 for k in range(12)]))
        tracker.close()
    torch.testing.assert_close(runs[1], runs[0], atol=1e-9, rtol=0)


# -- bursts ------------------------------------------------------------------------------------------
BURST_SCRIPT = textwrap.dedent("""
    import resource, sys, torch
    from torchevtrack.camera import Camera
    from torchevtrack.tracker import EventPoseTracker
    torch.set_num_threads(1)
    N, W, H = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    cam = Camera(W, H, 0.785 * W, 0.785 * W, (W - 1) / 2, (H - 1) / 2)
    g = torch.Generator().manual_seed(0)
    # A flicker burst: half the events on the border rows/columns, timestamps in 20 distinct values.
    x = torch.randint(0, W, (N,), generator=g); y = torch.randint(0, H, (N,), generator=g)
    side = torch.randint(0, 4, (N,), generator=g)
    x = torch.where(side == 0, (W - 1) * (x % 2), x)
    y = torch.where(side == 1, (H - 1) * (y % 2), y)
    del side
    t = torch.sort(torch.randint(0, 20, (N,), generator=g)).values * 100
    p = torch.randint(0, 2, (N,), generator=g)
    tr = EventPoseTracker(cam, "can")
    tr.reset(torch.tensor([0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0]))
    e = torch.zeros(0, dtype=torch.long)
    tr(e, e, e, e)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    pose = tr(x, y, t, p)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tr.close()
    ok = bool(torch.isfinite(pose).all()) and abs(float(pose[0, 3:].norm()) - 1) < 1e-9
    print(ok, (after - before) / 1024, after / 1024, int(tr.quality.events[0]))
""")


@pytest.mark.parametrize("n, width, height, max_growth_mb, max_peak_mb", [(150_000, 160, 120, 500, None),
                                                                         (10_000_000, 640, 480, None, 3000)])
def test_burst_in_one_window_does_not_crash_and_memory_stays_bounded(n, width, height, max_growth_mb, max_peak_mb):
    """A flicker burst in one 2 ms window, in a fresh process for an honest peak-RSS measurement.

    EROS updates in place with no temporaries and the flow stage matches long packets in chunks (its
    registration still holds its samples, ~0.5 per event here), so 1e7 events on 640x480 stay within
    3 GB for the whole process, inputs included."""
    out = subprocess.run([sys.executable, "-c", BURST_SCRIPT, str(n), str(width), str(height)], capture_output=True,
                         text=True, timeout=900, env={**os.environ, "PYOPENGL_PLATFORM": "egl"})
    assert out.returncode == 0, out.stderr[-2000:]
    ok, growth_mb, peak_mb, events = out.stdout.split()
    assert ok == "True" and int(events) == n
    if max_growth_mb is not None:
        assert float(growth_mb) < max_growth_mb, growth_mb
    if max_peak_mb is not None:
        assert float(peak_mb) < max_peak_mb, peak_mb


def _burst_stream(g, n, B, H, W, t0):
    """Moving edges (triplets) and uniform noise for ``B`` elements, packed; time order within each element."""
    k = torch.arange(n // 2)
    b = torch.randint(0, B, (n,), generator=g)
    edge_x = (k // H * (1 + b[: n // 2])) % W  # a vertical edge per element, stepping right at its own speed
    x = torch.cat((edge_x, torch.randint(0, W, (n - n // 2,), generator=g)))
    y = torch.cat((k % H, torch.randint(0, H, (n - n // 2,), generator=g)))
    t = torch.cat((k // H * 40, torch.randint(0, int(k[-1]) // H * 40 + 1, (n - n // 2,), generator=g)))
    order = torch.argsort(t, stable=True)
    return x[order], y[order], t0 + t[order], torch.randint(0, 2, (n,), generator=g), b[order]


@pytest.mark.parametrize("per_polarity, estimate, chunk, onset_us",
                         [(False, "normal", 97, 1000), (True, "register", 13, 0), (False, "register", 1, 50)])
def test_triplet_flow_in_chunks_equals_one_pass(per_polarity, estimate, chunk, onset_us):
    """Samples, SAE and flow field of a packet matched in chunks equal one pass over it, bit for bit."""
    B, H, W, n = 2, 30, 40, 2500
    g = torch.Generator().manual_seed(chunk)
    kw = dict(batch_size=B, block=10, min_samples=5, per_polarity=per_polarity, estimate=estimate, onset_us=onset_us)
    one, chunked = TripletFlow(H, W, **kw), TripletFlow(H, W, **kw, chunk=chunk)
    for i in range(3):
        x, y, t, p, b = _burst_stream(g, n, B, H, W, 200_000 * i)
        sae = one.sae.clone()
        ev, flow = triplet_samples(sae, x, y, t, p, b, onset_us=onset_us, last=one.newest.clone())  # one pass
        xi, yi, ch = _prepare(sae, x, y, t, p, b)
        ev_c, flow_c = chunked._match(xi, yi, ch, t)
        assert ev.numel() > 100 and torch.equal(ev_c, ev) and torch.equal(flow_c, flow)
        if not onset_us:
            assert torch.equal(chunked.sae, sae_update(sae, x, y, t, p, b))
        chunked.sae_padded.copy_(one.sae_padded)  # undo, then the whole forward in chunks
        chunked.last_padded.copy_(one.last_padded)
        a, c = one(x, y, t, p, b), chunked(x, y, t, p, b)
        assert a.valid.any()
        for field in a._fields:
            assert torch.equal(getattr(c, field), getattr(a, field)), field
        assert torch.equal(chunked.sae_padded, one.sae_padded) and torch.equal(chunked.last_padded, one.last_padded)


# -- objects out of view -----------------------------------------------------------------------------
@pytest.mark.parametrize("pose", [[1.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], [0.0, -0.5, 0.3, 0.0, 1.0, 0.0, 0.0],
                                  [0.0, 0.0, 40.0, 1.0, 0.0, 0.0, 0.0]])
def test_object_out_of_view_from_the_start(pose):
    tracker = EventPoseTracker(SMALL, "can")
    tracker.reset(torch.tensor(pose, dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    poses = torch.stack([tracker(*_noise(2000 * k, 200, g)) for k in range(15)])
    tracker.close()
    _assert_valid_poses(poses)


def test_object_moving_out_of_view():
    """Constant 5 m/s sideways and 5 rad/s, sparse noise events: the object leaves the 64x48 view."""
    tracker = EventPoseTracker(SMALL, "can", TrackerConfig().replace(**ABLATIONS["velocity_only"]))
    tracker.reset(POSE0, twist=torch.tensor([[5.0, 0.0, 0.0, 0.0, 0.0, 5.0]], dtype=torch.float64))
    tracker.velocity.Q.zero_()  # keep the twist: no flow will correct it
    tracker.velocity.rho = 1.0
    g = torch.Generator().manual_seed(1)
    poses = torch.stack([tracker(*_noise(2000 * k, 20, g)) for k in range(60)])[:, 0]
    tracker.close()
    _assert_valid_poses(poses)
    u = SMALL.project(poses[:, :3])[:, 0]
    assert u[0] < SMALL.width and u[-1] > SMALL.width + 30  # it really left (radius ~8 px)


def test_an_element_out_of_view_does_not_disturb_the_others(seq):
    """Batch windows share one render size: an off-screen element must not change its neighbour's poses
    (argmax rule: see tests/test_tracker.py::test_batch_elements_are_independent)."""
    cfg = TrackerConfig().replace(**ABLATIONS["no_ukf"]).replace(template={"rule": "argmax"})
    off = torch.tensor([1.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    single = EventPoseTracker(CAM, seq.mesh, cfg)
    single.reset(seq.gt_poses[0])
    pair = EventPoseTracker(CAM, [seq.mesh, seq.mesh], cfg)
    pair.reset(torch.stack((seq.gt_poses[0], off)))
    g = torch.Generator().manual_seed(2)
    for k in range(12):
        x, y, t, p = _window(seq.events, 2000 * k, 2000 * (k + 1))
        nx, ny, nt, npol = _noise(2000 * k, 300, g, CAM)
        a = single(x, y, t, p)
        b = torch.cat((torch.zeros(len(x), dtype=torch.long), torch.ones(300, dtype=torch.long)))
        ab = pair(torch.cat((x, nx)), torch.cat((y, ny)), torch.cat((t, nt)), torch.cat((p, npol)), b)
        torch.testing.assert_close(ab[0], a[0], atol=1e-5, rtol=0)
        _assert_valid_poses(ab, atol=1e-6)  # without the UKF the output is the float32 template pose
    single.close()
    pair.close()


# -- bad initial poses and meshes ---------------------------------------------------------------------
@pytest.mark.parametrize("pose, match", [
    ([float("inf"), 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], "NaN or infinite"),
    ([0.0, 0.0, 0.4, 0.0, 0.0, 0.0, 0.0], "unit"),
    ([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], "behind"),
    ([0.0, 0.0, 0.4, 1.0, 0.0, 0.0], r"shape \(\.\.\., 7\)"),
    ([[0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0]] * 3, r"shape \(1, 7\)"),
])
def test_invalid_initial_pose_is_a_clear_error(pose, match):
    tracker = EventPoseTracker(SMALL, "can")
    with pytest.raises(ValueError, match=match):
        tracker.reset(torch.tensor(pose, dtype=torch.float64))
    tracker.close()


@pytest.mark.parametrize("twist", [torch.full((1, 6), float("nan")), torch.zeros(5), [[0.0] * 6]])
def test_invalid_initial_twist_is_a_clear_error(twist):
    tracker = EventPoseTracker(SMALL, "can")
    try:
        with pytest.raises((ValueError, TypeError), match="twist"):
            tracker.reset(POSE0, twist=twist)
            g = torch.Generator().manual_seed(0)
            for k in range(5):
                tracker(*_noise(2000 * k, 300, g))
    finally:
        tracker.close()


def _degenerate(kind):
    if kind == "point":
        return trimesh.Trimesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]], process=False)
    if kind == "collinear":
        return trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    if kind == "nan":
        return trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [np.nan, 0, 0]], faces=[[0, 1, 2]], process=False)
    return trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0]], faces=np.zeros((0, 3), dtype=int), process=False)


@pytest.mark.parametrize("kind, match", [("point", "zero extent"), ("collinear", "zero area"),
                                         ("nan", "NaN or infinite"), ("no_faces", "empty")])
def test_degenerate_meshes_are_rejected(kind, match):
    with pytest.raises(ValueError, match=match):
        EventPoseTracker(SMALL, _degenerate(kind))


@pytest.mark.parametrize("name, content, err, match", [
    ("empty.obj", b"", ValueError, "empty"),
    ("bad.ply", b"hello, not a mesh", ValueError, "could not read a mesh"),
    ("missing.obj", None, FileNotFoundError, "not found"),
])
def test_unloadable_mesh_files_are_rejected(tmp_path, name, content, err, match):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(err, match=match):
        EventPoseTracker(SMALL, path)
    with pytest.raises(ValueError, match="unknown object"):
        EventPoseTracker(SMALL, "no_such_object")


def test_wrong_mesh_type_names_the_argument():
    with pytest.raises(TypeError, match="mesh"):
        EventPoseTracker(SMALL, 3)


# -- property-based: the event stages on arbitrary packets ------------------------------------------------
@st.composite
def packets(draw, max_events=60):
    H = draw(st.integers(1, 12))
    W = draw(st.integers(1, 12))
    B = draw(st.integers(1, 3))
    n = draw(st.integers(0, max_events))
    # Border pixels are likely: a coordinate is 0, the last index, or anything.
    coord = lambda size: st.one_of(st.sampled_from([0, size - 1]), st.integers(0, size - 1))  # noqa: E731
    x = draw(st.lists(coord(W), min_size=n, max_size=n))
    y = draw(st.lists(coord(H), min_size=n, max_size=n))
    b = draw(st.lists(st.integers(0, B - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.integers(0, 1), min_size=n, max_size=n))
    # Non-decreasing times with many repeats, from 0 or from Unix-epoch microseconds.
    t0 = draw(st.sampled_from([0, 1_700_000_000_000_000]))
    steps = draw(st.lists(st.sampled_from([0, 0, 0, 1, 7, 300, 20_000, 10**6]), min_size=n, max_size=n))
    t = t0 + np.cumsum(np.array(steps, dtype=np.int64))
    split = draw(st.integers(0, n))
    tensors = [torch.tensor(v, dtype=torch.long) for v in (x, y, b, p)]
    return H, W, B, (*tensors[:2], torch.from_numpy(t).long(), tensors[3], tensors[2]), split


def eros_oracle(H, W, B, x, y, b, k, decay):
    """Sequential per-event EROS (the definition)."""
    s = np.zeros((B, H, W))
    lam, r = decay ** (1.0 / k), k // 2
    for xi, yi, bi in zip(x.tolist(), y.tolist(), b.tolist()):
        s[bi, max(yi - r, 0):yi + r + 1, max(xi - r, 0):xi + r + 1] *= lam
        s[bi, yi, xi] = 1.0
    return s


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(packets(), st.sampled_from([1, 3, 5, 7]), st.floats(0.05, 0.95))
def test_eros_accepts_any_packet(packet, k, decay):
    H, W, B, (x, y, t, p, b), split = packet
    eros = EROS(H, W, kernel_size=k, decay=decay, batch_size=B)
    eros(x[:split], y[:split], b[:split])
    s = eros(x[split:], y[split:], b[split:])
    assert s.shape == (B, H, W) and torch.isfinite(s).all()
    assert float(s.min()) >= 0.0 and float(s.max()) <= 1.0
    np.testing.assert_allclose(s.numpy(), eros_oracle(H, W, B, x, y, b, k, decay), rtol=0, atol=1e-5)
    if min(H, W) >= 2:  # one-pixel-wide surfaces: see test_observation_of_a_one_pixel_wide_surface
        obs = eros.observation()
        assert obs.shape == (B, H, W) and float(obs.min()) >= 0.0 and float(obs.max()) <= 1.0


@pytest.mark.parametrize("shape", [(1, 5), (5, 1)])
def test_observation_of_a_one_pixel_wide_surface(shape):
    eros = EROS(*shape, kernel_size=3)
    eros(torch.tensor([0]), torch.tensor([0]))
    assert eros.observation().shape == (1, *shape)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(packets(), st.integers(1, 5), st.integers(1, 4), st.booleans(), st.sampled_from(["normal", "register"]),
       st.sampled_from([0, 1000]))
def test_triplet_flow_accepts_any_packet(packet, block, min_samples, per_polarity, estimate, onset_us):
    H, W, B, (x, y, t, p, b), split = packet
    flow = TripletFlow(H, W, batch_size=B, block=block, min_samples=min_samples, D=2, per_polarity=per_polarity,
                       estimate=estimate, onset_us=onset_us)
    G = flow.n_blocks
    for sl in (slice(0, split), slice(split, None)):
        out = flow(x[sl], y[sl], t[sl], p[sl], b[sl])
        assert out.uv.shape == (B, G, 2) and out.flow.shape == (B, G, 2) and out.valid.shape == (B, G)
        assert torch.isfinite(out.flow).all() and torch.isfinite(out.uv).all()
        assert torch.equal(out.valid, out.count >= min_samples)
        assert (out.flow[~out.valid] == 0).all()
    # Each pixel's latest event time (oracle: a loop), whether or not the event was matched.
    sae = np.full((B, 2 if per_polarity else 1, H, W), NEVER, dtype=np.int64)
    for xi, yi, ti, pi, bi in zip(x.tolist(), y.tolist(), t.tolist(), p.tolist(), b.tolist()):
        c = pi if per_polarity else 0
        sae[bi, c, yi, xi] = max(sae[bi, c, yi, xi], ti)
    np.testing.assert_array_equal(flow.newest.numpy(), sae)
