"""The tracker as an nn.Module: state_dict, copies, pickles and torch.save continue with the same poses; conversions
and updates it cannot run are refused with one clear message."""

import copy
import io
import pickle

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
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


@pytest.mark.parametrize("how", ["deepcopy", "pickle", "torch.save", "state_dict into a fresh tracker",
                                 "state_dict into a used tracker"])
def test_a_restored_tracker_continues_with_the_same_poses(seq, how):
    windows = _windows(seq)
    for pipeline in (False, True):
        def make():
            return EventPoseTracker(CAM, seq.mesh, pipeline=pipeline)

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
    assert all(after[k].dtype == v.dtype and after[k].device == v.device and torch.equal(after[k], v)
               for k, v in before.items())
    windows = _windows(seq)[:2]
    assert torch.isfinite(torch.stack([tracker(*w) for w in windows])).all()
    assert tracker.to("cpu") is tracker  # what it runs on is accepted
