"""The tracker as an nn.Module: state_dict, copies, pickles and torch.save continue with the same poses; conversions
and updates it cannot run are refused with one clear message."""

import copy
import io
import pickle

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
BEFORE, AFTER = 8, 8  # updates before the snapshot, and compared after it


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.04, seed=3, camera=CAM, progress=False)


def _windows(seq):
    t0 = int(seq.gt_t_us[0])
    out = []
    for k in range(BEFORE + AFTER):
        e = seq.events.slice_time(t0 + 2000 * k, t0 + 2000 * (k + 1))
        out.append((e.x, e.y, e.t, e.p))
    return out


def _run(tracker, windows):
    return np.stack([tracker(*w).numpy() for w in windows])


def _torch_save(tracker):
    buf = io.BytesIO()
    torch.save(tracker, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=False)


def _into(fresh_of, used, windows):
    def restore(tracker):
        other = fresh_of()
        if used:  # a tracker with a state of its own (other poses, a larger render window, inference tensors)
            pose = tracker.pose[0].clone()
            pose[2] += 0.05
            other.reset(pose)
            other(*windows[0])
        other.load_state_dict(tracker.state_dict())
        return other
    return restore


@pytest.mark.parametrize("config", [TrackerConfig(), TrackerConfig().replace(**ABLATIONS["full"]),
                                    TrackerConfig().replace(**ABLATIONS["hypotheses"])],
                         ids=["defaults", "ukf", "hypotheses"])  # the second holds a twin tracker and checks at 20 ms
@pytest.mark.parametrize("how", ["deepcopy", "pickle", "torch.save", "state_dict into a fresh tracker",
                                 "state_dict into a used tracker"])
def test_a_restored_tracker_continues_with_the_same_poses(seq, how, config):
    windows = _windows(seq)
    for pipeline in (False, True):
        def make():
            return EventPoseTracker(CAM, seq.mesh, config, pipeline=pipeline)

        reference = make()
        reference.reset(seq.gt_poses[0])
        expected = _run(reference, windows)[BEFORE:]

        original = make()
        original.reset(seq.gt_poses[0])
        _run(original, windows[:BEFORE])
        restore = {"deepcopy": copy.deepcopy, "pickle": lambda m: pickle.loads(pickle.dumps(m)),
                   "torch.save": _torch_save, "state_dict into a fresh tracker": _into(make, False, windows),
                   "state_dict into a used tracker": _into(make, True, windows)}[how]
        restored = restore(original)
        assert restored is not original
        assert np.array_equal(_run(restored, windows[BEFORE:]), expected), (how, pipeline)
        # the original is not disturbed by being saved or copied
        assert np.array_equal(_run(original, windows[BEFORE:]), expected), (how, pipeline)
        for t in (reference, original, restored):
            t.close()


@pytest.mark.parametrize("convert", [lambda m: m.to(torch.float32), lambda m: m.double(), lambda m: m.half(),
                                     lambda m: m.to("cuda"), lambda m: m.to("meta")],
                         ids=["to(float32)", "double", "half", "to(cuda)", "to(meta)"])
def test_conversions_the_kernels_cannot_run_are_refused_at_to_time(seq, convert):
    tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
    tracker.reset(seq.gt_poses[0])
    before = {k: v.clone() for k, v in tracker.state_dict().items()}
    with pytest.raises(ValueError, match="EventPoseTracker runs on the CPU in its own dtypes") as err:
        convert(tracker)
    assert "\n" not in str(err.value)
    after = tracker.state_dict()  # nothing converted, and the tracker still runs
    assert all(after[k].dtype == v.dtype and after[k].device == v.device and torch.equal(after[k].isnan(), v.isnan())
               and torch.equal(after[k].nan_to_num(), v.nan_to_num()) if v.is_floating_point() else torch.equal(after[k], v)
               for k, v in before.items())  # NaN marks "no rate yet" in the burst guard
    windows = _windows(seq)[:2]
    assert torch.isfinite(torch.stack([tracker(*w) for w in windows])).all()
    assert tracker.to("cpu") is tracker  # what it runs on is accepted


def test_forward_before_reset_says_to_call_reset(seq):
    tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
    with pytest.raises(RuntimeError, match=r"call reset\(pose\) before the first update"):
        tracker(*_windows(seq)[0])


def _bad_windows(seq):
    """(name, window, message) of windows forward and track must refuse."""
    x, y, t, p = _windows(seq)[1]
    n = len(t)
    shuffled = torch.cat([t[n // 2:], t[:n // 2]])
    return [
        ("unsorted", (x, y, shuffled, p), "t goes back in time at event"),
        ("negative t", (x, y, t - int(t[-1]) - 1, p), "t=-"),
        ("polarity 2", (x, y, t, torch.where(torch.arange(n) == 3, 2, p.long())), "event 3 has p=2, a polarity"),
        ("polarity -1", (x, y, t, torch.where(torch.arange(n) == 3, -1, p.long())), "event 3 has p=-1"),
        ("x outside", (torch.where(torch.arange(n) == 5, CAM.width, x.long()), y, t, p), "event 5 has x=320"),
        ("float seconds", (x, y, t.double() * 1e-6, p), "t must be an integer tensor microseconds"),
        # in the kernels' dtypes (the fast path)
        ("int8 polarity -1", (x, y, t, torch.where(torch.arange(n) == 4, -1, p).to(torch.int8)), "event 4 has p=-1"),
        ("int16 y outside", (x, torch.where(torch.arange(n) == 6, CAM.height, y).to(torch.int16), t, p),
         "event 6 has y=240"),
    ]


@pytest.mark.parametrize("case", range(8))
def test_forward_and_track_refuse_bad_windows(seq, case):
    name, window, message = _bad_windows(seq)[case]
    tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
    tracker.reset(seq.gt_poses[0])
    tracker(*_windows(seq)[0])
    state = {k: v.clone() for k, v in tracker.state_dict().items()}
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        tracker(*window)
    assert all(torch.equal(v, tracker.state_dict()[k]) for k, v in state.items())  # nothing went in
    from torchevtrack.events import EventStream
    with pytest.raises(ValueError, match="stream 0: .*" + message.replace("(", r"\(")):
        tracker.track(EventStream(*window), seq.gt_poses[0], progress=False)


def test_time_going_back_across_windows_is_refused(seq):
    windows = _windows(seq)
    for batch in (False, True):
        def b(w):
            return torch.zeros(len(w[0]), dtype=torch.long) if batch else None

        tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
        tracker.reset(seq.gt_poses[0])
        tracker(*windows[1], b(windows[1]))
        with pytest.raises(ValueError, match="t goes back in time across windows at event 0"):
            tracker(*windows[0], b(windows[0]))


def test_a_wrong_length_batch_index_names_the_tensors(seq):
    tracker = EventPoseTracker(CAM, seq.mesh, batch_size=2, pipeline=False, workers=1)
    tracker.reset(seq.gt_poses[0])
    x, y, t, p = _windows(seq)[0]
    with pytest.raises(ValueError, match=f"b has {len(t) - 1} events, t has {len(t)}: x, y, t, p, b must have"):
        tracker(x, y, t, p, torch.zeros(len(t) - 1, dtype=torch.long))


def test_int32_windows_are_cast_once_and_give_the_same_poses(seq):
    import torchevtrack.update as intake  # the intake's compiled kernels

    def signatures():
        return {name: list(k.signatures) for name, k in vars(intake).items() if hasattr(k, "signatures")}

    windows = _windows(seq)[:4]
    runs, seen = [], []
    for cast in (lambda v: v, lambda v: v.to(torch.int32)):
        tracker = EventPoseTracker(CAM, seq.mesh, pipeline=False)
        tracker.reset(seq.gt_poses[0])
        runs.append(np.stack([tracker(*(cast(v) for v in w)).numpy() for w in windows]))
        seen.append(signatures())
    assert np.array_equal(runs[0], runs[1])
    assert seen[0] and seen[1] == seen[0]  # the int32 windows compiled no new signature
