"""Tracking-loss detector: synthetic quality sequences against a sequential reference implementation,
the re-initialisation hook, the ground-truth comparison, and an end-to-end run on a synthetic sequence."""

import copy
import math
import pickle

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.loss import LossDetector, compare_with_ground_truth
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker, Quality

P = dict(score_threshold=0.3, min_flow_vectors=3, patience=5, recovery=3, ema=0.1)


def quality(score, flow, rejected=None):
    score = torch.as_tensor(score, dtype=torch.float32).reshape(-1)
    flow = torch.as_tensor(flow, dtype=torch.int64).reshape(-1)
    rejected = torch.zeros_like(flow, dtype=torch.bool) if rejected is None else torch.as_tensor(rejected).reshape(-1)
    return Quality(score, flow, torch.full_like(flow, 100), rejected)


class ReferenceDetector:
    """One element, one update at a time, written from the rule's description."""

    def __init__(self, score_threshold, min_flow_vectors, patience, recovery, ema, initial_reference=None):
        self.th, self.nmin, self.patience, self.recovery, self.ema = (score_threshold, min_flow_vectors, patience,
                                                                      recovery, ema)
        self.ref = initial_reference
        self.low_run = self.good_run = 0
        self.lost = False

    def step(self, score, flow, rejected):
        score = float(np.float32(score))  # the tracker's scores are float32
        if math.isnan(score):
            c_score = 1.0
        else:
            if self.ref is None and score > 0:
                self.ref = score
            c_score = 0.0 if self.ref is None else min(max(score / self.ref, 0.0), 1.0)
        c_flow = 1.0 if self.nmin == 0 else min(flow / self.nmin, 1.0)
        conf = 0.0 if rejected else min(c_score, c_flow)
        low = rejected or c_score < self.th or flow < self.nmin
        if not low and not math.isnan(score):
            self.ref = (1 - self.ema) * self.ref + self.ema * score
        if low:
            self.low_run, self.good_run = self.low_run + 1, 0
        else:
            self.low_run, self.good_run = 0, self.good_run + 1
        if self.low_run >= self.patience:
            self.lost = True
        if self.good_run >= self.recovery:
            self.lost = False
        return conf, self.lost


def test_good_then_degraded_is_lost_after_exactly_patience_low_updates():
    det = LossDetector(1, **P)
    for i in range(20):
        out = det(quality([3.0 + 0.1 * (i % 3)], [6]), 2000 * i)
        assert not bool(out.lost[0]) and float(out.confidence[0]) > 0.9
    ref = float(det.reference[0])
    for k in range(1, P["patience"] + 1):
        out = det(quality([0.5], [6]), 2000 * (20 + k))  # 0.5 / 3 < 0.3
        assert bool(out.lost[0]) == (k == P["patience"]), k
        assert float(out.confidence[0]) == pytest.approx(0.5 / ref)
    assert bool(out.newly_lost[0]) and int(det.lost_at_us[0]) == 2000 * (20 + P["patience"])
    assert float(det.reference[0]) == ref  # low scores never enter the reference
    # Recovery: `recovery` confident updates in a row.
    for k in range(1, P["recovery"] + 1):
        out = det(quality([2.9], [6]), 2000 * (30 + k))
        assert bool(out.lost[0]) == (k < P["recovery"])
    assert int(det.lost_at_us[0]) == 2000 * (20 + P["patience"])  # the first loss stays on record


def test_the_detectors_views_follow_copies_pickles_and_new_buffers():
    """The detector's kernel updates its buffers through numpy views (:class:`~torchevtrack.stages.BufferViews`): a
    copy, a pickle, buffers moved to new storage or new buffer tensors must be the ones updated."""
    det = LossDetector(1, **P)
    det(quality([3.0], [6]), 0)  # the views are made
    twin, thawed = copy.deepcopy(det), pickle.loads(pickle.dumps(det))
    det.share_memory()
    moved = LossDetector(1, **P)
    moved(quality([3.0], [6]), 0)
    moved.low_run = torch.zeros(1, dtype=torch.int64)  # a new buffer tensor
    moved.lost = torch.zeros(1, dtype=torch.bool)
    for d in (det, twin, thawed, moved):
        for k in range(1, P["patience"] + 1):
            out = d(quality([0.1], [6]), 2000 * k)
        assert bool(out.lost[0]) and bool(d.lost[0]) and int(d.low_run[0]) == P["patience"]
        assert int(d.lost_at_us[0]) == 2000 * P["patience"]
    assert int(LossDetector(1, **P).low_run[0]) == 0


def test_missing_flow_alone_leads_to_loss():
    det = LossDetector(1, **P)
    for i in range(10):
        det(quality([3.0], [4]), i)
    lost = [bool(det(quality([3.0], [2]), 10 + i).lost[0]) for i in range(P["patience"])]
    assert lost == [False] * (P["patience"] - 1) + [True]
    assert float(det.confidence[0]) == pytest.approx(2 / 3)


def test_interrupted_low_runs_do_not_accumulate():
    det = LossDetector(1, **P)
    det(quality([3.0], [5]), 0)
    for i in range(40):  # patience - 1 low updates, then one good one, repeatedly
        low = i % P["patience"] != P["patience"] - 1
        assert not bool(det(quality([0.1 if low else 3.0], [5]), i + 1).lost[0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_sequential_reference_on_random_sequences(seed):
    g = torch.Generator().manual_seed(seed)
    B, T = 4, 300
    # Regimes that switch every ~20 updates: good, bad score, no flow, rejected, NaN score.
    regime = torch.randint(0, 5, (B, T // 20 + 1), generator=g).repeat_interleave(20, 1)[:, :T]
    score = 2.0 + torch.rand(B, T, generator=g)
    score = torch.where(regime == 1, 0.3 * torch.rand(B, T, generator=g), score)
    score = torch.where(regime == 4, torch.tensor(float("nan")), score)
    score[:, 0] = torch.where(torch.rand(B, generator=g) < 0.5, -0.2, score[:, 0])  # a start without reference
    flow = torch.randint(3, 9, (B, T), generator=g)
    flow = torch.where(regime == 2, torch.randint(0, 3, (B, T), generator=g), flow)
    rejected = (regime == 3) & (torch.rand(B, T, generator=g) < 0.7)
    det = LossDetector(B, **P)
    refs = [ReferenceDetector(**P) for _ in range(B)]
    n_lost = 0
    for i in range(T):
        out = det(quality(score[:, i], flow[:, i], rejected[:, i]), 1000 * i)
        for b in range(B):
            conf, lost = refs[b].step(float(score[b, i]), int(flow[b, i]), bool(rejected[b, i]))
            assert float(out.confidence[b]) == pytest.approx(conf, rel=1e-9, abs=1e-12), (i, b)
            assert bool(out.lost[b]) == lost, (i, b)
            n_lost += lost
    assert 0 < n_lost < B * T  # the sequences exercise both states


def test_elements_are_independent_and_reset_by_mask():
    seqs = [[(3.0, 5)] * 12, [(3.0, 5)] * 4 + [(0.1, 5)] * 8, [(3.0, 0)] * 12]
    batched = LossDetector(3, **P)
    singles = [LossDetector(1, **P) for _ in seqs]
    for i in range(12):
        out = batched(quality([s[i][0] for s in seqs], [s[i][1] for s in seqs]), i)
        for b, d in enumerate(singles):
            o = d(quality([seqs[b][i][0]], [seqs[b][i][1]]), i)
            assert bool(o.lost[0]) == bool(out.lost[b]) and float(o.confidence[0]) == float(out.confidence[b])
    assert batched.lost.tolist() == [False, True, True]
    batched.reset(torch.tensor([False, True, False]))
    assert batched.lost.tolist() == [False, False, True] and math.isnan(float(batched.reference[1]))
    assert int(batched.low_run[1]) == 0 and int(batched.lost_at_us[1]) == -1
    batched.reset(torch.tensor([2]))
    assert not batched.lost.any()


def test_nan_score_and_disabled_flow():
    det = LossDetector(1, **{**P, "min_flow_vectors": 0})
    for i in range(10):
        out = det(quality([float("nan")], [0]), i)
    assert not bool(out.lost[0]) and float(out.confidence[0]) == 1.0 and math.isnan(float(det.reference[0]))
    for i in range(P["patience"]):
        out = det(quality([float("nan")], [0], [True]), 10 + i)
        assert float(out.confidence[0]) == 0.0
    assert bool(out.lost[0])


def test_initial_reference_flags_a_bad_start():
    det = LossDetector(1, **P, initial_reference=2.0)
    outs = [det(quality([0.4], [5]), i) for i in range(P["patience"])]
    assert [bool(o.lost[0]) for o in outs] == [False] * (P["patience"] - 1) + [True]
    learned = LossDetector(1, **P)  # without it, the first score becomes the reference
    assert not any(bool(learned(quality([0.4], [5]), i).lost[0]) for i in range(3 * P["patience"]))


def test_on_lost_reinitialises_the_elements_it_returns_poses_for():
    calls = []
    pose = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)

    def on_lost(idx, t_us):
        calls.append((idx.tolist(), t_us.tolist()))
        return pose.expand(len(idx), 7) if 1 in idx.tolist() else None

    det = LossDetector(3, **P, on_lost=on_lost)
    det(quality([3.0, 3.0, 3.0], [5, 5, 5]), torch.tensor([0, 10, 20]))
    for i in range(1, P["patience"] + 1):
        out = det(quality([3.0, 0.1, 0.1], [5, 5, 5]), torch.tensor([i, 10 + i, 20 + i]))
        assert out.reinit_index.numel() == (2 if i == P["patience"] else 0)
    p = P["patience"]
    assert calls == [([1, 2], [10 + p, 20 + p])]
    assert out.reinit_index.tolist() == [1, 2] and torch.equal(out.reinit_pose, pose.expand(2, 7))
    assert out.lost.tolist() == [False, True, True]  # the state that triggered the call
    assert det.lost.tolist() == [False, False, False]  # the re-initialised elements start over
    assert det.lost_at_us.tolist() == [-1, 10 + p, 20 + p]
    # Stays quiet for an element that remains lost (called once per loss).
    calls.clear()
    det2 = LossDetector(1, **P, on_lost=lambda i, t: calls.append(1))
    for i in range(3 * P["patience"]):
        det2(quality([0.1], [0]), i)
    assert calls == [1] and bool(det2.lost[0])


@pytest.mark.parametrize("ret, match", [
    (torch.zeros(2, 7), r"shape \(1, 7\)"),
    (torch.tensor([[0.0, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0]]), "unit"),
])
def test_on_lost_bad_poses(ret, match):
    det = LossDetector(1, **{**P, "patience": 1}, on_lost=lambda i, t: ret)
    with pytest.raises(ValueError, match=match):
        det(quality([0.0], [0]), 0)


@pytest.mark.parametrize("kwargs, match", [
    ({"batch_size": 0}, "batch_size"),
    ({"batch_size": 1, "patience": 0}, "patience"),
    ({"batch_size": 1, "score_threshold": 0.0}, "score_threshold"),
    ({"batch_size": 1, "ema": 1.5}, "ema"),
    ({"batch_size": 1, "initial_reference": -1.0}, "initial_reference"),
    ({"batch_size": 1, "min_flow_vectors": -1}, "min_flow_vectors"),
])
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LossDetector(**kwargs)


def test_bad_update_inputs():
    det = LossDetector(2)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        det(quality([1.0], [3]), 0)
    with pytest.raises(TypeError, match="microseconds"):
        det(quality([1.0, 1.0], [3, 3]), 0.5)
    with pytest.raises(ValueError, match="indices"):
        det.reset(torch.tensor([2]))


# -- ground-truth comparison ------------------------------------------------------------------------
def _gt(n=200):
    t = torch.arange(n, dtype=torch.int64) * 2000
    gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(n, 7).clone()
    return t, gt


def test_compare_with_ground_truth_delay_and_outcomes():
    t, gt = _gt()
    pred = gt.clone()
    pred[80:, 0] += 0.10  # 10 cm off from sample 80 on: the failure run starts at 80
    lost = torch.zeros(200, dtype=torch.bool)
    lost[95:] = True
    r = compare_with_ground_truth(t, lost, pred, t, gt)
    assert r == {"first_loss_us": 190_000, "first_failure_us": 160_000, "delay_us": 30_000, "missed": False,
                 "false_alarm": False, "declarations": 1, "false_alarms": 0, "recoveries": 0, "tracked_us": 398_000}
    r = compare_with_ground_truth(t, torch.zeros(200, dtype=torch.bool), pred, t, gt)
    assert r["missed"] and r["first_loss_us"] is None and r["delay_us"] is None
    r = compare_with_ground_truth(t, lost, gt, t, gt)
    assert r["false_alarm"] and r["first_failure_us"] is None
    # declared twice before the failure and found again in between: the first is a false alarm, the second, still
    # held when the failure run starts (sample 80), detects it early
    flicker = torch.zeros(200, dtype=torch.bool)
    flicker[10:20] = True
    flicker[30:] = True
    r = compare_with_ground_truth(t, flicker, pred, t, gt)
    assert (r["declarations"], r["false_alarms"], r["recoveries"]) == (2, 1, 1)
    assert (r["first_loss_us"], r["delay_us"], r["missed"]) == (20_000, -100_000, False)
    # a false alarm found again before the failure does not detect it: the declaration after the failure does
    late = torch.zeros(200, dtype=torch.bool)
    late[10:20] = True
    late[90:] = True
    r = compare_with_ground_truth(t, late, pred, t, gt)
    assert (r["declarations"], r["false_alarms"], r["recoveries"]) == (2, 1, 1)
    assert (r["first_loss_us"], r["delay_us"], r["missed"]) == (20_000, 20_000, False)
    early = torch.zeros(200, dtype=torch.bool)
    early[10:20] = True  # ... and without it the failure is missed
    r = compare_with_ground_truth(t, early, pred, t, gt)
    assert (r["false_alarms"], r["delay_us"], r["missed"], r["false_alarm"]) == (1, None, True, False)
    # found again exactly when the failure run starts: closed by then, a false alarm
    edge = torch.zeros(200, dtype=torch.bool)
    edge[70:80] = True
    r = compare_with_ground_truth(t, edge, pred, t, gt)
    assert (r["false_alarms"], r["missed"]) == (1, True)
    # A 40-sample excursion is not a failure under the 50-sample rule, but is with window=30.
    short = gt.clone()
    short[10:50, 0] += 0.10
    assert compare_with_ground_truth(t, lost, short, t, gt)["first_failure_us"] is None
    assert compare_with_ground_truth(t, lost, short, t, gt, window=30)["first_failure_us"] == 20_000
    with pytest.raises(ValueError, match="bool"):
        compare_with_ground_truth(t, lost.long(), pred, t, gt)


def _turned(gt, axis, deg):
    """``gt`` turned by ``deg`` about the object-frame ``axis`` (the quaternion product written out)."""
    h = math.radians(deg) / 2
    a = torch.tensor(axis, dtype=torch.float64)
    w2, v2 = math.cos(h), math.sin(h) * a / a.norm()
    w1, v1 = gt[:, 3], gt[:, 4:]
    out = gt.clone()
    out[:, 3] = w1 * w2 - v1 @ v2
    out[:, 4:] = w1[:, None] * v2 + v2.new_tensor(w2) * v1 + torch.linalg.cross(v1, v2.expand_as(v1), dim=-1)
    return out


def test_compare_with_ground_truth_leaves_a_spin_about_the_symmetry_axis_out():
    """A can spun 90 deg about its axis from sample 80 fails the plain rule, not the rule modulo the axis; tipped
    90 deg about another axis it fails both."""
    t, gt = _gt()
    spun, tipped = gt.clone(), gt.clone()
    spun[80:] = _turned(gt[80:], (0.0, 0.0, 1.0), 90.0)
    tipped[80:] = _turned(gt[80:], (1.0, 0.0, 0.0), 90.0)
    lost = torch.zeros(200, dtype=torch.bool)
    lost[120:] = True
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    plain = compare_with_ground_truth(t, lost, spun, t, gt)
    assert (plain["first_failure_us"], plain["delay_us"], plain["false_alarm"]) == (160_000, 80_000, False)
    sym = compare_with_ground_truth(t, lost, spun, t, gt, symmetry_axis=axis)
    assert (sym["first_failure_us"], sym["missed"], sym["false_alarm"]) == (None, False, True)
    assert compare_with_ground_truth(t, lost, tipped, t, gt, symmetry_axis=axis) == \
        compare_with_ground_truth(t, lost, tipped, t, gt)


# -- end to end -------------------------------------------------------------------------------------
CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
CUT_US = 60_000


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.14, seed=3, camera=CAM, progress=False)


def _noise(t0, t1, n, seed):
    g = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.randint(t0, t1, (n,), generator=g)).values
    return EventStream.from_arrays(torch.randint(0, CAM.width, (n,), generator=g),
                                   torch.randint(0, CAM.height, (n,), generator=g), t,
                                   torch.randint(0, 2, (n,), generator=g))


def test_end_to_end_loss_is_flagged_only_for_broken_streams(seq):
    """Three copies of one sequence: intact; events replaced by noise after 60 ms; no events after 60 ms."""
    ev = seq.events
    t_end = int(seq.gt_t_us[-1])
    head = ev.slice_time(0, CUT_US)
    rate = len(head) / CUT_US
    streams = [ev, EventStream.concat([head, _noise(CUT_US, t_end, int(rate * (t_end - CUT_US)), 0)]), head]
    tracker = EventPoseTracker(CAM, seq.mesh, batch_size=3)
    det = LossDetector(3)  # defaults: patience 25 updates (50 ms at 500 Hz)
    try:
        tracker.reset(seq.gt_poses[0])
        period = tracker.period_us
        times, lost, poses = [], [], []
        for k in range(1, t_end // period + 1):
            parts = [s.slice_time((k - 1) * period, k * period) for s in streams]
            b = torch.cat([torch.full((len(q),), i, dtype=torch.long) for i, q in enumerate(parts)])
            x, y, t, p = (torch.cat([getattr(q, f) for q in parts]).long() for f in "xytp")
            poses.append(tracker(x, y, t, p, b))
            out = det(tracker.quality, k * period)
            times.append(k * period)
            lost.append(out.lost)
    finally:
        tracker.close()
    times, lost, poses = torch.tensor(times), torch.stack(lost, 1), torch.stack(poses, 1)
    assert not lost[0].any()  # the intact stream is never flagged
    for b in (1, 2):
        first = int(times[lost[b].nonzero()[0, 0]])
        # Flagged once `patience` updates of no support have passed, not before the cut.
        assert CUT_US + 25 * period <= first <= CUT_US + 35 * period, (b, first)
        assert lost[b, times >= first].all()
    r = compare_with_ground_truth(times, lost[0], poses[0], seq.gt_t_us, seq.gt_poses)
    assert r["first_loss_us"] is None and r["first_failure_us"] is None and not r["false_alarm"]


def test_update_times_take_one_time_or_one_per_element():
    from torchevtrack.loss import update_times

    assert update_times(5, 3).tolist() == [5, 5, 5]
    assert update_times(torch.tensor([1, 2, 3]), 3).tolist() == [1, 2, 3]
    with pytest.raises(TypeError, match="integer microseconds"):
        update_times(1.5, 3)
    with pytest.raises(ValueError, match=r"one per element \(3\)"):
        update_times(torch.tensor([1, 2]), 3)
