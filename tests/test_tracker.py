"""End-to-end tracker tests on a small synthetic sequence (320x240 box, regular motion)."""

import math
import threading

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.metrics import evaluate
from torchevtrack.online import OnlineTracker
from torchevtrack.stages.propagate import propagate
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
DURATION_S = 0.12


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", DURATION_S, seed=3, camera=CAM, progress=False)


def _track(seq, config=None, batch=1, workers=None):
    tracker = EventPoseTracker(CAM, [seq.mesh] * batch, config, workers=workers)
    times, poses = tracker.track([seq.events] * batch, seq.gt_poses[0], t_start_us=int(seq.gt_t_us[0]),
                                 t_end_us=int(seq.gt_t_us[-1]), progress=False)
    tracker.close()
    return times, poses


def test_full_tracker_follows_the_ground_truth(seq):
    times, poses = _track(seq)
    assert times.shape == (1, int(DURATION_S * 500)) and poses.shape == times.shape + (7,)
    assert torch.isfinite(poses).all()
    assert torch.allclose(poses[0, :, 3:].norm(dim=-1), torch.ones(times.shape[1], dtype=torch.float64), atol=1e-9)
    m = evaluate(times[0], poses[0], seq.gt_t_us, seq.gt_poses)
    # The object moves several cm in this clip; holding the initial pose is the trivial baseline.
    frozen = evaluate(times[0], seq.gt_poses[:1].expand(times.shape[1], 7), seq.gt_t_us, seq.gt_poses)
    assert m["rmse_t_cm"] < 2.0 and m["rmse_r_deg"] < 5.0, m
    assert m["rmse_t_cm"] < 0.6 * frozen["rmse_t_cm"], (m, frozen)
    assert not m["failed"]


def test_the_correction_moves_the_depth_at_most_its_speed_bound_per_update(seq):
    # the correction alone (no flow twist, no UKF: each update's start is the last output), started 1 cm too far: the
    # depth comes back, by at most template.max_depth_speed x the period per update; unbounded it moves further
    cfg = TrackerConfig().replace(velocity={"source": "none"}, ukf={"enabled": False})
    start = seq.gt_poses[:1].clone()
    start[0, 2] += 0.01
    steps = {}
    for speed in (0.5, math.inf):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg.replace(template={"max_depth_speed": speed}))
        _, poses = tracker.track(seq.events, start, t_start_us=int(seq.gt_t_us[0]), progress=False)
        tracker.close()
        steps[speed] = torch.cat((poses[0, :1, 2] - start[0, 2], poses[0, :, 2].diff())).abs()
    assert float(steps[0.5].max()) <= 0.5 * 0.002 * (1 + 1e-6) and float(steps[0.5].sum()) > 0.005
    assert float(steps[math.inf].max()) > 0.002


def test_with_the_ukf_the_depth_bound_follows_the_last_measurement(seq):
    # the correction alone (zero twist: each prediction is the last output) with the UKF, started 1 cm too far: the
    # UKF's output lags its measurements, and the band is centred at the last measurement (the output plus
    # depth_lag), so each measured depth is within the bound of the one before and comes back at the bound's speed
    # (a band around the lagging output gives steps of a quarter of the bound here: the lag eats the rest)
    speed = 0.5
    cfg = TrackerConfig().replace(velocity={"source": "none"}, ukf={"enabled": True},
                                  template={"max_depth_speed": speed})
    start = seq.gt_poses[0].clone()
    start[2] += 0.01
    tracker = EventPoseTracker(CAM, seq.mesh, cfg)
    tracker.reset(start)
    t0, measured = int(seq.gt_t_us[0]), [float(start[2])]
    for k in range(60):
        e = seq.events.slice_time(t0 + 2000 * k, t0 + 2000 * (k + 1))
        tracker(e.x, e.y, e.t, e.p)
        measured.append(float(tracker.pose[0, 2] + tracker.depth_lag[0]))
    steps = torch.tensor(measured, dtype=torch.float64).diff().abs()
    assert float(steps.max()) <= speed * 0.002 * (1 + 1e-6) and float(steps.sum()) > 0.005
    assert float(steps[3:15].mean()) > 0.8 * speed * 0.002, steps[:15]
    assert float(tracker.depth_lag.abs().max()) > 1e-4
    tracker.reset(start)
    assert float(tracker.depth_lag.abs().max()) == 0.0
    tracker.close()


def test_batch_elements_are_independent(seq):
    # With the argmax rule: its whole steps absorb the float32 rounding differences (~1e-8 m) between batch
    # sizes, which the Newton rule's sub-step moves carry on (and the tracker's feedback then amplifies).
    cfg = TrackerConfig().replace(**ABLATIONS["no_ukf"]).replace(template={"rule": "argmax"})
    t1, p1 = _track(seq, cfg)
    t2, p2 = _track(seq, cfg, batch=2)
    assert torch.equal(t2[0], t1[0]) and torch.equal(t2[1], t1[0])
    torch.testing.assert_close(p2[0], p1[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(p2[1], p1[0], atol=1e-5, rtol=0)


def test_worker_threads_do_not_change_the_poses(seq):
    # three elements (started 0, 2 and 4 mm off) over one, two and three threads: the same poses, bit for bit
    start = seq.gt_poses[0].expand(3, 7).clone()
    start[:, 0] += torch.tensor([0.0, 0.002, 0.004], dtype=start.dtype)

    def poses(workers):
        tracker = EventPoseTracker(CAM, seq.mesh, batch_size=3, workers=workers)
        out = tracker.track([seq.events] * 3, start, progress=False)[1]
        tracker.close()
        return out

    ref = poses(1)
    assert not torch.equal(ref[0], ref[2])
    for workers in (2, 3):
        assert torch.equal(poses(workers), ref)

    # packets interleaved in time across the elements (not grouped by element, as track packs them)
    def interleaved(workers):
        tracker = EventPoseTracker(CAM, seq.mesh, batch_size=3, workers=workers)
        tracker.reset(start)
        out = []
        for k in range(10):
            ev = seq.events.slice_time(int(seq.gt_t_us[0]) + 2000 * k, int(seq.gt_t_us[0]) + 2000 * (k + 1))
            order = torch.sort(ev.t.repeat(3), stable=True).indices
            b = torch.arange(3).repeat_interleave(len(ev))[order]
            x, y, t, p = (f.long().repeat(3)[order] for f in (ev.x, ev.y, ev.t, ev.p))
            out.append(tracker(x, y, t, p, b))
        tracker.close()
        return torch.stack(out)

    assert torch.equal(interleaved(2), interleaved(1))
    with pytest.raises(ValueError, match="workers"):
        EventPoseTracker(CAM, seq.mesh, workers=0)


def test_the_bound_steps_follow_new_buffers(seq):
    """The update's steps are bound to numpy views of the tracker's buffers. Buffers replaced by new tensors
    mid-stream (``_apply``, as ``.to()`` does) are read and written from then on: the poses continue bit for bit
    as those of an untouched tracker (a stale binding would update the old buffers and leave the new ones)."""
    t0 = int(seq.gt_t_us[0])
    windows = [seq.events.slice_time(t0 + k * 2000, t0 + (k + 1) * 2000) for k in range(25)]
    poses = []
    for replace in (False, True):
        tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
        tracker.reset(seq.gt_poses[0])
        out = []
        for i, w in enumerate(windows):
            if replace and i == 10:
                old = tracker.eros.surface
                tracker._apply(lambda t: t.clone())
                assert tracker._run.bound is None and tracker.eros.surface is not old
            out.append(tracker(w.x, w.y, w.t, w.p))
        if replace:
            assert not torch.equal(old, tracker.eros.surface)  # the new surface took the later events
        poses.append(torch.stack(out))
        tracker.close()
    assert torch.equal(poses[0], poses[1])


def test_a_deep_copy_tracks_on_its_own_buffers(seq):
    """A copy (``copy.deepcopy``, without threads) binds its own steps: its updates leave the original as it was and
    give the original's poses."""
    import copy

    t0 = int(seq.gt_t_us[0])
    windows = [seq.events.slice_time(t0 + k * 2000, t0 + (k + 1) * 2000) for k in range(12)]
    tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
    tracker.reset(seq.gt_poses[0])
    for w in windows[:6]:
        tracker(w.x, w.y, w.t, w.p)
    twin = copy.deepcopy(tracker)
    state = {k: v.clone() for k, v in tracker.state_dict().items()}
    got = torch.stack([twin(w.x, w.y, w.t, w.p) for w in windows[6:]])
    assert all(torch.equal(v, tracker.state_dict()[k]) for k, v in state.items())
    expected = torch.stack([tracker(w.x, w.y, w.t, w.p) for w in windows[6:]])
    assert torch.equal(got, expected)
    tracker.close()
    twin.close()


def test_empty_windows_keep_a_valid_pose():
    tracker = EventPoseTracker(CAM, "can")
    pose0 = torch.tensor([0.01, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    tracker.reset(pose0)
    e = torch.zeros(0, dtype=torch.long)
    for _ in range(5):
        pose = tracker(e, e, e, e)
    tracker.close()
    torch.testing.assert_close(pose[0], pose0, atol=1e-6, rtol=0)  # float32 templates


def test_updates_run_without_autograd_but_return_ordinary_tensors(seq):
    # the update runs in inference mode (also in the worker threads); what it returns, and the state a caller may
    # touch afterwards (a reset of one element between updates), stay usable outside it
    tracker = EventPoseTracker(CAM, seq.mesh, batch_size=2, workers=2)
    start = seq.gt_poses[0].expand(2, 7).clone()
    tracker.reset(start)
    t0 = int(seq.gt_t_us[0])
    for k in range(3):
        ev = seq.events.slice_time(t0 + 2000 * k, t0 + 2000 * (k + 1))
        x, y, t, p = (f.long().repeat(2) for f in (ev.x, ev.y, ev.t, ev.p))
        pose = tracker(x, y, t, p, torch.arange(2).repeat_interleave(len(ev)))
        if k == 1:
            tracker.reset(start, mask=torch.tensor([False, True]))
    tracker.close()
    assert not pose.is_inference() and pose.shape == (2, 7)
    delta = torch.zeros(2, 7, dtype=pose.dtype, requires_grad=True)
    (pose + delta).sum().backward()  # usable in a differentiable computation
    assert torch.equal(delta.grad, torch.ones_like(pose))


@pytest.mark.parametrize("bad, match", [
    ([0.0, 0.0, 0.4, 2.0, 0.0, 0.0, 0.0], "unit"),
    ([0.0, 0.0, -0.4, 1.0, 0.0, 0.0, 0.0], "behind"),
    ([float("nan"), 0.0, 0.4, 1.0, 0.0, 0.0, 0.0], "NaN"),
])
def test_invalid_initial_pose_is_rejected(bad, match):
    tracker = EventPoseTracker(CAM, "can")
    with pytest.raises(ValueError, match=match):
        tracker.reset(torch.tensor(bad))
    tracker.close()


def test_stream_count_must_match_batch():
    tracker = EventPoseTracker(CAM, ["can", "box"])
    ev = EventStream.from_arrays([1], [1], [10], [1])
    with pytest.raises(ValueError, match="expected 2 event streams"):
        tracker.track([ev], torch.tensor([0.0, 0.0, 0.4, 1.0, 0.0, 0.0, 0.0]))
    tracker.close()


def test_invalid_updates_keep_the_last_pose():
    """A velocity that throws the object behind the camera within one period is rejected."""
    tracker = EventPoseTracker(CAM, "can", TrackerConfig().replace(**ABLATIONS["velocity_only"]))
    pose0 = torch.tensor([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    tracker.reset(pose0, twist=torch.tensor([[0.0, 0.0, -500.0, 0.0, 0.0, 0.0]], dtype=torch.float64))
    tracker.velocity.Q.zero_()  # keep the absurd twist
    tracker.velocity.rho = 1.0
    e = torch.zeros(0, dtype=torch.long)
    pose = tracker(e, e, e, e)
    assert bool(tracker.quality.rejected[0])
    torch.testing.assert_close(pose[0], pose0)
    assert set(tracker.stage_ms) == {"eros", "flow", "velocity", "render", "correction", "ukf"}
    tracker.close()


def test_observation_drops_old_pixels_and_weighs_recent_ones(seq, monkeypatch):
    """The observation the tracker corrected against, captured from its kernel, against a per-pixel reference:
    EROS, zero where the last event is ``max_age_us`` old or older, times ``exp(-age / recency_us)``, then the
    3x3 median over the window under the canvas box, resampled into the canvas."""
    from torchevtrack import update
    from torchevtrack.stages.eros import observation
    from torchevtrack.stages.template import to_canvas

    seen, boxes = [], []
    kernel = update.canvas_kernel

    def capture(*args):  # canvas_kernel(surface, last, box, t_now, ..., out)
        kernel(*args)
        seen.append(torch.from_numpy(args[-1].copy()))
        boxes.append(torch.from_numpy(args[2].copy()))

    monkeypatch.setattr(update, "canvas_kernel", capture)
    cfg = TrackerConfig().replace(eros={"max_age_us": 4000, "recency_us": 1500.0})
    tracker = EventPoseTracker(CAM, seq.mesh, cfg)
    tracker.reset(seq.gt_poses[0])
    ev = seq.events.slice_time(int(seq.gt_t_us[0]), int(seq.gt_t_us[0]) + 10_000)
    t = ev.t.long()
    tracker(ev.x.long(), ev.y.long(), t, ev.p.long())
    tracker.close()
    t_now, box, N = tracker.t_last, boxes[0], cfg.template.canvas
    cu, cv, side = box[0].tolist()
    first, last = (0.5 - N / 2) * side / N, (N / 2 - 0.5) * side / N  # the canvas' outermost samples
    u0, v0 = max(math.floor(cu + first), 0), max(math.floor(cv + first), 0)
    u1, v1 = min(math.floor(cu + last) + 2, CAM.width), min(math.floor(cv + last) + 2, CAM.height)
    ref = torch.zeros(v1 - v0, u1 - u0)
    sae = tracker.flow.sae[0].amax(0)
    for v in range(v0, v1):
        for u in range(u0, u1):
            age = int(t_now[0]) - int(sae[v, u])
            if age < 4000:
                ref[v - v0, u - u0] = float(tracker.eros.surface[0, v, u]) * math.exp(-age / 1500.0)
    assert len(seen) == 1
    got = seen[0]
    want = to_canvas(observation(ref[None]), box, N, (u0, v0))
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)
    assert float(ref.gt(0).float().mean()) > 0.005  # the window holds recent edges
    with pytest.raises(ValueError, match="recency_us"):
        TrackerConfig().replace(eros={"recency_us": -1.0})


def test_the_observation_window_follows_the_last_updates_flow(seq, monkeypatch):
    """With ``eros.recency_px`` (the default), each update observes with the window the previous update's flow asked
    for (the first with ``recency_us``): the windows the correction's kernel was given, against the flow fields the
    recency stage was given and the reference of that stage's test; a moving object's windows move."""
    from torchevtrack import update
    from torchevtrack.stages import eros as eros_module

    from test_eros import _follow_reference

    used = []
    kernel = update.canvas_kernel

    def capture(*args):
        taus, level = args[5], args[7]
        used.append(float(taus[level[0]]))
        kernel(*args)

    monkeypatch.setattr(update, "canvas_kernel", capture)
    flows, follow = [], eros_module._follow_kernel

    def recorded(flow, valid, *args):
        flows.append((torch.from_numpy(flow.copy()), torch.from_numpy(valid.copy())))
        return follow(flow, valid, *args)

    monkeypatch.setattr(eros_module, "_follow_kernel", recorded)
    e = TrackerConfig().eros
    assert e.recency_px > 0  # the default
    tracker = EventPoseTracker(CAM, seq.mesh, TrackerConfig(), pipeline=False)
    t0 = int(seq.gt_t_us[0])
    tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 60_000, progress=False)
    tracker.close()
    assert len(used) == len(flows) == 30
    want = e.recency_us
    for k, (flow, valid) in enumerate(flows):
        assert used[k] == want, k
        ref = _follow_reference(flow, valid, e.recency_px, e.recency_min_us, e.recency_max_us)[0]
        want = want if ref is None else 250.0 * round(ref / 250.0)
    assert len(set(used)) >= 2  # the window moved off the first one


def test_correction_feedback_runs_only_with_flow_and_correction(seq):
    """The feedback needs both the flow twist it adds to and the corrections it integrates; the paper's
    ablations without either (and gain 0) run without it, the full method with it."""
    on = TrackerConfig().replace(velocity={"feedback_gain": 0.1})
    for name, want in (("full", True), ("no_ukf", True), ("velocity_only", False), ("correction_only", False),
                       ("edopt_vel", False)):
        tracker = EventPoseTracker(CAM, seq.mesh, on.replace(**ABLATIONS[name]))  # merged into `on`
        assert (tracker.feedback is not None) == want, name
        tracker.close()
    assert TrackerConfig().velocity.feedback_gain > 0  # on by default
    off = EventPoseTracker(CAM, seq.mesh, TrackerConfig().replace(velocity={"feedback_gain": 0.0}))
    assert off.feedback is None
    off.close()
    with pytest.raises(ValueError, match="feedback_axes"):
        TrackerConfig().replace(velocity={"feedback_axes": ["vz", "spin"]})


def test_feedback_ignores_turns_about_a_symmetry_axis():
    """An untextured cylinder hides turns about its axis: the tracker finds that axis, and a correction
    rate about it (camera frame) leaves the feedback at zero, while the textured built-in can has none."""
    import trimesh

    cyl = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48)
    tracker = EventPoseTracker(CAM, [cyl, "can"], TrackerConfig().replace(velocity={"feedback_gain": 0.1}))
    axes = tracker._symmetry_axis
    assert torch.allclose(axes[0].abs(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6)
    assert not axes[1].any()
    spin = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 0.0, 0.0, 2.0]], dtype=torch.float64)
    b = tracker.feedback(spin, axes)  # both objects at the identity: object axis = camera axis
    assert b[0].abs().max() < 1e-12 and b[1, 5] == 0.0  # (wz is not a feedback axis by default)
    tilt = torch.tensor([[0.0, 0.0, 0.0, 2.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    tracker.feedback.reset()
    b = tracker.feedback(tilt, axes)
    assert torch.allclose(b[:, 3], torch.full((2,), 0.2, dtype=torch.float64))
    tracker.close()


# -- the pipeline: part of each update on a thread of its own -------------------------------------
def _counting_intake(monkeypatch):
    """Count the windows the pipeline's thread takes in: ahead (its calls of the intake kernel) and into the EROS side
    with the observation (the observe kernel); the serial update calls the intake kernel on the caller's thread."""
    import threading

    import torchevtrack.stages.eros as observe_module
    import torchevtrack.update as intake_module

    calls = {"intake": [], "observe": []}
    for name, module, attr in (("intake", intake_module, "_intake_kernel"), ("observe", observe_module,
                                                                              "_observe_kernel")):
        def counted(*args, kernel=getattr(module, attr), name=name):
            if threading.current_thread() is not threading.main_thread():
                calls[name].append(1)
            return kernel(*args)

        monkeypatch.setattr(module, attr, counted)
    return calls


@pytest.mark.parametrize("ablation", ["full", "velocity_only", "correction_only", "full_fixed_recency"])
def test_the_pipeline_gives_the_poses_of_the_serial_update(seq, ablation, monkeypatch):
    """Bit for bit, one stream and a batch on one worker. Every window but the first goes in on the pipeline's
    thread: taken in ahead, or (one stream with its template made ahead) into the EROS side with the observation."""
    calls = _counting_intake(monkeypatch)
    cfg = TrackerConfig().replace(eros={"recency_px": 0.0}) if ablation == "full_fixed_recency" else \
        TrackerConfig().replace(**ABLATIONS[ablation])
    t0, t1 = int(seq.gt_t_us[0]), int(seq.gt_t_us[0]) + 40_000
    for batch in (1, 2):
        out = {}
        observes = batch == 1 and cfg.template.enabled
        for pipeline in (False, True):
            tracker = EventPoseTracker(CAM, [seq.mesh] * batch, cfg, workers=1, pipeline=pipeline)
            calls["intake"].clear(), calls["observe"].clear()
            out[pipeline] = tracker.track([seq.events] * batch, seq.gt_poses[0], t_start_us=t0, t_end_us=t1,
                                          progress=False)[1]
            tracker.close()
            n = out[pipeline].shape[1] - 1 if pipeline else 0
            assert (len(calls["intake"]), len(calls["observe"])) == ((0, n) if observes else (n, 0))
        assert torch.equal(out[True], out[False])


def test_pipeline_options_and_a_window_that_was_not_taken_in(seq, monkeypatch):
    with pytest.raises(ValueError, match="workers=1"):
        EventPoseTracker(CAM, [seq.mesh] * 2, workers=2, pipeline=True)
    assert not EventPoseTracker(CAM, [seq.mesh] * 2, workers=2)._schedule.pipelined  # the workers use the cores
    # (with render.ahead, one stream's windows go into the EROS side on that thread instead of ahead)
    tracker = EventPoseTracker(CAM, seq.mesh, TrackerConfig().replace(render={"ahead": False}), workers=1,
                               pipeline=True)
    tracker.reset(seq.gt_poses[0])
    w = [seq.events.slice_time(int(seq.gt_t_us[0]) + k * 2000, int(seq.gt_t_us[0]) + (k + 1) * 2000)
         for k in range(3)]
    win = [(e.x, e.y, e.t, e.p, None) for e in w]
    tracker(*win[0], next_window=win[1])
    with pytest.raises(RuntimeError, match="taken in ahead"):
        tracker(*win[2])
    # A track that stops early (here: an error in an update) leaves nothing taken in ahead behind.
    import torchevtrack.update as output_module

    kernel = output_module._output_kernel

    def failing(*args):
        failing.n += 1
        if failing.n == 3:
            raise FloatingPointError("stop")
        return kernel(*args)

    failing.n = 0
    monkeypatch.setattr(output_module, "_output_kernel", failing)
    with pytest.raises(FloatingPointError):
        tracker.track(seq.events, seq.gt_poses[0], progress=False)
    assert tracker._run.ahead is None
    monkeypatch.setattr(output_module, "_output_kernel", kernel)
    tracker.reset(seq.gt_poses[0])
    assert tracker(*win[0]).shape == (1, 7)
    tracker.close()


# -- render.ahead: the template rendered where the previous update predicted --------------------------
def _recording(monkeypatch):
    """Record each update's prediction and twist (the motion kernel's outputs) and the pose each element's template
    was rendered at (the compiled rasteriser's binding makes the model with the render, one element per call)."""
    import torchevtrack.update as update_module

    rec = {"motion": [], "render_pose": []}
    motion, render_model = update_module._motion_kernel, update_module.RenderModelBinding.__call__

    def motion_recorded(*args):
        out = motion(*args)
        predicted, twist = args[-4:-2]
        rec["motion"].append((torch.from_numpy(predicted.copy()), torch.from_numpy(twist.copy())))
        return out

    def render_model_recorded(self, pose, shaded, model):
        if model:
            rec["render_pose"].append(torch.from_numpy(pose.copy()).float())
        return render_model(self, pose, shaded, model)

    monkeypatch.setattr(update_module, "_motion_kernel", motion_recorded)
    monkeypatch.setattr(update_module.RenderModelBinding, "__call__", render_model_recorded)
    return rec


@pytest.mark.parametrize("batch", [1, 2])
def test_render_ahead_renders_where_the_last_update_predicted(seq, batch, monkeypatch):
    rec = _recording(monkeypatch)
    cfg = TrackerConfig().replace(render={"ahead": True})
    tracker = EventPoseTracker(CAM, [seq.mesh] * batch, cfg, workers=1, pipeline=False)
    t0 = int(seq.gt_t_us[0])
    tracker.track([seq.events] * batch, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 20_000, progress=False)
    tracker.close()
    calls = rec["render_pose"]
    renders = [torch.cat(calls[i:i + batch]) for i in range(0, len(calls), batch)]  # per update
    first = rec["motion"][0][0]
    assert len(renders) == 10 and torch.equal(renders[0], first.float())  # nothing predicted before the first
    for (pred, twist), render_pose in zip(rec["motion"], renders[1:]):
        assert torch.equal(render_pose, propagate(pred, twist, 0.002).float())
    # the search still starts from the new prediction, which the corrections move off the rendered pose
    assert any(not torch.equal(r, p.float()) for r, (p, _) in zip(renders[1:], rec["motion"][1:]))


def test_render_ahead_made_on_the_intake_thread_gives_the_serial_poses(seq, monkeypatch):
    """With the pipeline the next update's render and template model are made on the intake thread during this
    update, also across online pushes that complete one window each, and a reset drops them: bit for bit the
    serial poses. (In track, with the next window to take in, the thread renders only: the pipeline tests above.)"""
    import torchevtrack.tracker as tracker_module

    made = []
    render_soon = tracker_module.EventPoseTracker._render_soon
    monkeypatch.setattr(tracker_module.EventPoseTracker, "_render_soon",
                        lambda self, *a, **kw: made.append(kw["model"]) or render_soon(self, *a, **kw))
    cfg = TrackerConfig().replace(render={"ahead": True})
    t0 = int(seq.gt_t_us[0])
    restart = seq.gt_poses[20].clone()
    out = {}
    for pipeline in (False, True):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg, workers=1, pipeline=pipeline)
        online = OnlineTracker(tracker)
        online.start(seq.gt_poses[0], t0)
        got = []
        for a in range(t0, t0 + 40_000, 2000):  # one window per push: nothing to take in ahead, a render to make
            got += online.push(seq.events.slice_time(a, a + 2000))
            if a == t0 + 20_000:  # a restart moves the pose: the render made for the old one must not be used
                tracker.reset(restart)
        out[pipeline] = torch.stack([p for _, p in got])
        assert made == ([True] * 19 if pipeline else [])  # with no window to take in, the model is made there too
        made.clear()
        tracker.close()
    assert torch.equal(out[True], out[False])


def test_a_failed_render_ahead_raises_in_the_update_that_needs_it_once(seq):
    tracker = EventPoseTracker(CAM, seq.mesh, workers=1, pipeline=True)
    tracker.reset(seq.gt_poses[0])
    binding = tracker._render_one
    make = binding.kernel

    at = make.py_func.__code__.co_varnames.index("model")

    def failing_once(*args):  # the compiled call
        on_thread = threading.current_thread() is not threading.main_thread()
        if args[at] and on_thread and not failing_once.failed:  # a render with its model made on the thread
            failing_once.failed = True
            raise MemoryError("no memory for the render")
        return make(*args)

    failing_once.failed = False
    binding.kernel = failing_once
    t0 = int(seq.gt_t_us[0])
    w = [seq.events.slice_time(t0 + k * 2000, t0 + (k + 1) * 2000) for k in range(3)]
    tracker(w[0].x, w[0].y, w[0].t, w[0].p)  # renders at once, and its successor's render on the thread, which fails
    with pytest.raises(MemoryError, match="no memory"):
        tracker(w[1].x, w[1].y, w[1].t, w[1].p)
    assert tracker._run.rendering is None  # taken: the next update renders again rather than raise the same error
    assert torch.isfinite(tracker(w[2].x, w[2].y, w[2].t, w[2].p)).all()
    tracker.close()


def test_the_tracker_renders_what_the_renderer_renders(seq):
    """One stream renders through one compiled call (RenderModelBinding): bit for bit RasterRenderer.render of the
    same pose and window."""
    tracker = EventPoseTracker(CAM, seq.mesh)
    pose = seq.gt_poses[:1].clone()
    pose[:, 3:] *= 1.0004  # not quite unit: both normalise it the same way
    tracker.reset(pose)
    want = tracker._renderers[0].render(pose, roi=tuple(tracker._windows(pose.numpy())[0].tolist()), shaded=False)
    assert torch.equal(tracker.depth, want.depth) and float(want.depth.max()) > 0
    tracker.close()


# -- a fast turn with sensor noise: what the defaults hold that the earlier ones lost -------------------------
# The defaults before the interior template, the image-speed recency window, the slower velocity decays and the 1 deg
# rotation step (TrackerConfig as it was when the wide suite showed every turn lost).
EARLIER = TrackerConfig().replace(template={"interior": 0.0, "dtheta_deg": 0.5},
                                  velocity={"rho": 0.5, "rho_turn": 0.5, "r_px": 1.0, "r_rel": 0.0},
                                  eros={"recency_px": 0.0, "recency_max_us": 10000.0})


def _noisy_turn(seed: int, configs: dict[str, TrackerConfig]) -> dict[str, dict]:
    """0.4 s of the built-in box turned at 240-440 deg/s about wandering axes (the ``turn`` group), 640x480, 1 Hz per
    pixel of background noise and a 50 us refractory period, tracked from the true start with each config:
    ``evaluate``'s figures per config name."""
    vga = Camera(640, 480, 502.3, 502.3, 319.5, 239.5)
    seq = generate_sequence("box", "turn", 0.4, seed=seed, camera=vga, noise_rate_hz=1.0, refractory_us=50,
                            render_backend="raster", progress=False)
    result = {}
    for name, config in configs.items():
        tracker = EventPoseTracker(vga, seq.mesh, config)
        times, poses = tracker.track(seq.events, seq.gt_poses[0], t_start_us=int(seq.gt_t_us[0]), progress=False)
        tracker.close()
        result[name] = evaluate(times[0], poses[0], seq.gt_t_us, seq.gt_poses)
    return result


@pytest.mark.parametrize("seed", [3, 15])
def test_a_fast_noisy_turn_is_held_by_the_defaults_and_not_by_the_earlier_ones(seed):
    """A fast noisy turn (:func:`_noisy_turn`). The earlier defaults are lost by the EDOPT rule (seed 15, 4.8 cm /
    48 deg RMSE) or 3.6 cm / 16 deg off (seed 3); the defaults hold both at about 1 cm and within 10 deg. Over seeds
    0-15 of this setting the mean RMSE went from 2.2 cm / 18 deg to 1.6 cm / 6 deg and the runs lost from 2 to 1
    (docs/notebook.md, 2026-12-01 afternoon; the seed then lost, 8, is the next test's)."""
    result = _noisy_turn(seed, {"earlier": EARLIER, "defaults": TrackerConfig()})
    now, before = result["defaults"], result["earlier"]
    assert not now["failed"] and now["rmse_t_cm"] <= 1.2 and now["rmse_r_deg"] <= 10.0, now
    assert before["failed"] or (before["rmse_t_cm"] > 3.0 and before["rmse_r_deg"] > 10.0), before


def test_a_steady_turn_lost_with_one_decay_is_held_when_pitch_and_yaw_follow_it():
    """Seed 8 of :func:`_noisy_turn`: with one decay for every axis (``velocity.rho_turn = rho``, the model before)
    the run is lost by the EDOPT rule (4.6 cm / 40 deg RMSE); with the defaults (the UKF on, as measured), whose pitch
    and yaw rates keep their value while the rotation keeps its axis, it is held (1.7 cm / 13 deg). Over seeds 0-23 of
    this setting: 2 runs lost -> 1, mean RMSE 2.68 cm / 7.1 deg -> 2.43 cm / 5.1 deg (docs/notebook.md, 2026-12-02
    evening; this seed's figures at ``velocity.robust_k`` 0.5 and ``velocity.r_rel`` 0.2, 2026-12-02 late)."""
    full = TrackerConfig().replace(**ABLATIONS["full"])  # with the UKF, as these figures were measured
    one_decay = full.replace(velocity={"rho_turn": full.velocity.rho})
    result = _noisy_turn(8, {"one decay": one_decay, "defaults": full})
    assert result["one decay"]["failed"], result["one decay"]
    assert not result["defaults"]["failed"] and result["defaults"]["rmse_r_deg"] < 20.0, result["defaults"]
