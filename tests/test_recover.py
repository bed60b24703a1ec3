"""Recovery (torchevtrack.recover): a lost element keeps the tracker's own pose and its flag, is searched for only while
events come, restarts where the search is clear and beats the tracker's pose, and is found again where the search
confirms that pose; ``track`` (recovering unless ``--no-recover``) writes the lost flags beside the poses.

The restart tests replace the wide search (:class:`~torchevtrack.stages.relocalise.Relocaliser`, tested on its own in
tests/test_relocalise.py) by an oracle that returns the true pose, clear: they test what the recoverer does with a
search's result (when it searches, the masked restart, the reported pose and flag), not the search itself.
"""

import copy
import dataclasses
import math

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.geometry import interpolate_poses, perturb_pose, quat_to_matrix
from torchevtrack.io.lost import lost_path, read_lost
from torchevtrack.io.poses import read_tum
from torchevtrack.mesh import load_mesh
from torchevtrack.metrics import adds_error, mesh_points, per_pose_errors
from torchevtrack.raster import RasterRenderer
from torchevtrack import recover
from torchevtrack.recover import TWIST_SPAN_US, bookkeeping_kernel, found_again, turned_poses, wholly_in_view
from torchevtrack.stages.propagate import twist_between
from torchevtrack.stages.eros import canvas_observation
from torchevtrack.stages.relocalise import Relocalisation, Relocaliser
from torchevtrack.stages.template import area_weight
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
GAP_US = (100_000, 300_000)  # the blackout, after the first pose
RECOVER = TrackerConfig().replace(loss={"enabled": True}, recover={"enabled": True})
CAP = RECOVER.recover.max_cost_px  # the clear-winner cost


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.42, seed=3, camera=CAM, progress=False)


def blackout(seq, start_us: int, end_us: int):
    """``seq`` without the events of ``[t0 + start_us, t0 + end_us)``."""
    t0, ev = int(seq.gt_t_us[0]), seq.events
    return dataclasses.replace(seq, events=ev.select((ev.t < t0 + start_us) | (ev.t >= t0 + end_us)))


@pytest.fixture
def truth_search(seq, monkeypatch):
    """The relocaliser replaced by an oracle: the true pose at the search time, clear and far below the tracker's own
    pose's cost; records ``(t_us, centre)``."""
    calls = []

    def search(self, pose, last_us, t_now_us, own=None):
        calls.append((int(t_now_us[0]), pose[0].clone()))
        found = interpolate_poses(seq.gt_t_us, seq.gt_poses, t_now_us)
        return Relocalisation(found, torch.zeros(1, dtype=torch.float64), torch.full((1,), math.inf),
                              torch.ones(1, dtype=torch.bool), torch.full((1,), math.inf))

    monkeypatch.setattr(Relocaliser, "forward", search)
    return calls


def errors(seq, times, poses):
    e = per_pose_errors(times, poses, seq.gt_t_us, seq.gt_poses)
    return e["t_us"], e["te"], torch.rad2deg(e["re"])


def test_after_a_blackout_the_search_restarts_the_lost_element_on_the_object(seq, truth_search):
    dark = blackout(seq, *GAP_US)
    t0 = int(seq.gt_t_us[0])
    back = t0 + GAP_US[1]
    moved = float((interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([back]))[0, :3]
                   - interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t0 + GAP_US[0]]))[0, :3]).norm())
    assert moved > 0.03  # the object moved several cm in the dark
    end = back + 100_000
    runs = {}
    for name, cfg, events in (("clean", TrackerConfig(), seq.events),
                              ("plain", TrackerConfig().replace(loss={"enabled": True}), dark.events),
                              ("recover", RECOVER, dark.events)):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg)
        times, poses = tracker.track(events, seq.gt_poses[0], t_start_us=t0, t_end_us=end, progress=False)
        runs[name] = (times[0], poses[0], tracker.lost)
        tracker.close()
    # 100 ms after the events return: as far from the truth as the uninterrupted run (the tracker's own accuracy on
    # this small image, about 1-2 cm here), the run without the search farther (how far is chaotic: 2.7 cm to far
    # off, by the CPU and the kernels' cache)
    err = {name: [float(v[-1]) for v in errors(seq, *runs[name][:2])[1:]] for name in runs}
    assert err["plain"][0] > err["recover"][0] + 0.01, err
    assert err["recover"][0] <= err["clean"][0] + 0.005 and err["recover"][1] <= err["clean"][1] + 2.0, err
    assert not runs["recover"][2][0]
    # no search in the dark (no recent events), the first one soon after the events returned
    searched = [c[0] for c in truth_search]
    assert searched and min(searched) >= back and min(searched) <= back + 20_000
    # lost in the dark: its output is the tracker's own, as without recovery (no search, no restart before the
    # events return), and the last good pose is kept aside
    outputs = {}
    for name, cfg in (("plain", TrackerConfig().replace(loss={"enabled": True})), ("recover", RECOVER)):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg)
        outputs[name] = [v[0] for v in tracker.track(dark.events, seq.gt_poses[0], t_start_us=t0, t_end_us=back,
                                                     progress=False, return_lost=True)]
        good = None if tracker.recover is None else tracker.recover.good_pose[0].clone()
        tracker.close()
    times, poses, lost = outputs["recover"]
    assert lost[-1] and (lost & (times > t0 + GAP_US[0])).sum() > 50
    assert torch.equal(poses, outputs["plain"][1]) and torch.equal(lost, outputs["plain"][2])
    assert not torch.equal(poses[lost][0], poses[lost][-1])  # the tracker's pose moves on in the dark
    first_lost = int(lost.nonzero()[0, 0])
    assert float((good[:3] - poses[first_lost - 1, :3]).norm()) < 0.01  # (the last good update came before)


def test_the_real_search_restarts_a_noisy_640x480_box_after_a_blackout_at_the_default_clear_cost():
    """End to end, no oracle: 200 ms without events while a box moves, with sensor noise (10 Hz per pixel); 100 ms
    after the events return the tracker is within 1 cm / 5 deg with the default clear-winner cost (5 px), and not with
    the 3 px of before (noise events far from every model edge raise the found pose's chamfer cost above 3 px, as at
    1280x720 with noise; with 1.5 px no search was clear even without noise)."""
    vga = Camera(640, 480, 502.3, 502.3, 319.5, 239.5)
    box = generate_sequence("box", "regular", 0.52, seed=3, camera=vga, noise_rate_hz=10.0, progress=False)
    dark, t0 = blackout(box, 200_000, 400_000), int(box.gt_t_us[0])
    end = t0 + 500_000
    result = {}
    for cost in (3.0, RECOVER.recover.max_cost_px):
        tracker = EventPoseTracker(vga, box.mesh, RECOVER.replace(recover={"max_cost_px": cost}))
        times, poses = tracker.track(dark.events, box.gt_poses[0], t_start_us=t0, t_end_us=end, progress=False)
        tracker.close()
        _, te, re = errors(box, times[0], poses[0])
        result[cost] = (float(te[-1]), float(re[-1]), tracker.recover.restarts)
    assert RECOVER.recover.max_cost_px == 5.0
    assert result[5.0][0] <= 0.01 and result[5.0][1] <= 5.0 and result[5.0][2] >= 1, result
    assert result[3.0][0] > 0.01 and result[3.0][2] == 0, result


def test_an_object_that_left_the_view_is_searched_for_and_restarted_when_it_returns():
    """End to end, no oracle: the box slides out of the image (0.15-0.5 s), stays out 0.1 s and slides back (0.6-0.95
    s; ``generate_sequence(leave_view=...)``). The tracker loses it; with recovery it is flagged lost and searched for
    once it is back, and never wrong in silence: at the end it is either found (within 3 cm ADD-S, up to the box's
    symmetries, and not flagged) or still flagged. Which of the two is chaotic on this small image and differs between
    CPUs (numba compiles for the host's vector units) and even between kernel caches of one machine: on AVX-512
    machines a restart came in 2-3 of 7 seeds of this scene (right or 74-162 deg off); on an AVX2 machine each
    search's best ties with a pose 3-4 cm away (the last, at 0.986 s: 1.71 against 1.74 px, 3 deg apart) and none is
    clear, and with another cache the tracker finds the box by itself. The benchmarks' leaving-the-view trials
    measure how often it is found, not this test."""
    away = generate_sequence("box", "regular", 1.3, seed=5, camera=CAM, leave_view=(0.15, 0.1), progress=False)
    assert away.meta["leave_view"] == {"start_s": 0.15, "away_s": 0.1}
    points = mesh_points(away.mesh.vertices)
    tracker = EventPoseTracker(CAM, away.mesh, RECOVER)
    times, poses, lost = tracker.track(away.events, away.gt_poses[0], progress=False, return_lost=True)
    tracker.close()
    truth = interpolate_poses(away.gt_t_us, away.gt_poses, times[0][-1:])
    end = times[0] > times[0][-1] - 100_000  # the last 0.1 s
    error = float(adds_error(poses[0][-1:], truth, points)[0])
    assert bool(lost[0].any()) and tracker.recover.searches >= 1
    assert bool(lost[0][end].any()) or error < 0.03, error  # found, or still flagged


def test_a_depth_drift_the_loss_detector_does_not_see_is_flagged_by_the_depth_check(seq):
    """End to end, no oracle: a start 25 % too far along the line of sight, with the correction's depth speed bounded
    (2 cm/s) so that the tracker cannot undo it and its template score stays confident (the detector never declares
    it lost). The depth check (``recover.check_us``) finds a rival scaled back onto the object that costs clearly less
    at its first three checks: the run is flagged from the first (``check_us`` after the start) on, and only reported:
    no search, the same poses as without the check, whose run is never flagged. From the true start no check flags."""
    t0, check = int(seq.gt_t_us[0]), RECOVER.recover.check_us
    drifted = seq.gt_poses[0].clone()
    drifted[:3] *= 1.25
    runs = {}
    for name, start, check_us in (("drifted", drifted, check), ("no check", drifted, 0),
                                  ("truth", seq.gt_poses[0], check)):
        cfg = RECOVER.replace(recover={"check_us": check_us}, template={"max_depth_speed": 0.02})
        tracker = EventPoseTracker(CAM, seq.mesh, cfg)
        times, poses, lost = tracker.track(seq.events, start, t_start_us=t0, t_end_us=t0 + 3 * check + 10_000,
                                           progress=False, return_lost=True)
        tracker.close()
        runs[name] = (times[0] - t0, poses[0], lost[0], tracker.recover)
    assert check > 0
    t, poses, lost, rec = runs["drifted"]
    _, te, _ = errors(seq, t + t0, poses)
    assert float(te.min()) > 0.05  # drifted throughout
    assert rec.checks == 3 and rec.searches == 0 and rec.restarts == 0
    assert not bool(lost[t < check].any()) and bool(lost[t >= check].all()), t[lost]
    assert not bool(rec.lost.any()) and bool(rec.drifted.all())
    _, plain, never, unchecked = runs["no check"]
    assert torch.equal(plain, poses) and not bool(never.any()) and unchecked.checks == 0
    t, _, lost, rec = runs["truth"]
    assert rec.checks == 3 and not bool(lost.any()) and not bool(rec.drifted.any())


def test_a_depth_check_needs_the_whole_object_in_view():
    """The projected bounding sphere (radius r at depth z: half-size f r / (z - r) px) must lie inside the frame."""
    reloc = Relocaliser(RasterRenderer(load_mesh("box"), CAM), 0.05)
    half = CAM.fx * 0.05 / (0.5 - 0.05)  # 27.9 px
    inside = lambda u: wholly_in_view(torch.tensor([[(u - CAM.cx) * 0.5 / CAM.fx, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]],
                                                   dtype=torch.float64), reloc)
    assert inside(CAM.cx) and inside(half + 2) and inside(CAM.width - half - 3)
    assert not inside(half - 2) and not inside(CAM.width - half + 1) and not inside(-40.0)
    behind = torch.tensor([[0.0, 0.0, 0.07, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)  # within 1.5 radii
    assert not wholly_in_view(behind, reloc)


def test_isolated_noise_is_no_edge_to_search_in(seq, truth_search):
    """While only isolated events come (every third pixel of every third row, each firing every 10 ms: thousands of
    recent pixels, none with a recent neighbour), a lost element is not searched; the first search comes within one
    retry after the object's events return, and restarts it there (the oracle)."""
    t0 = int(seq.gt_t_us[0])
    ev = seq.events
    v, u = torch.meshgrid(torch.arange(1, CAM.height - 1, 3), torch.arange(1, CAM.width - 1, 3), indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    ticks = torch.arange(t0 + 100_000, t0 + 300_000, 10_000)
    t = (ticks[:, None] + torch.arange(len(u)) % 10_000).reshape(-1)  # each pixel at its own phase
    order = t.argsort()
    noise = EventStream(u.repeat(len(ticks))[order].short(), v.repeat(len(ticks))[order].short(), t[order],
                        torch.ones(len(t), dtype=torch.int8))
    events = EventStream.concat([ev.select(ev.t < t0 + 100_000), noise, ev.select(ev.t >= t0 + 300_000)])
    tracker = EventPoseTracker(CAM, seq.mesh, RECOVER)
    times, poses, lost = tracker.track(events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 400_000,
                                       progress=False, return_lost=True)
    tracker.close()
    assert bool(lost[0][(times[0] > t0 + 200_000) & (times[0] < t0 + 300_000)].all())  # lost among the noise
    searched = [c[0] for c in truth_search]
    assert searched and min(searched) >= t0 + 300_000 and min(searched) <= t0 + 300_000 + RECOVER.recover.retry_us
    assert tracker.recover.restarts >= 1


def test_a_start_search_moves_a_wrong_start_into_the_basin(seq, truth_search):
    t0 = int(seq.gt_t_us[0])
    start = perturb_pose(seq.gt_poses[0], 0.02, math.radians(10.0), torch.Generator().manual_seed(4))
    end = t0 + 200_000
    cfg = RECOVER.replace(recover={"start_search": True})
    results = {}
    for name, c in (("plain", RECOVER), ("start search", cfg), ("twin", cfg.replace(**ABLATIONS["hypotheses"]))):
        tracker = EventPoseTracker(CAM, seq.mesh, c)
        times, poses = tracker.track(seq.events, start, t_start_us=t0, t_end_us=end, progress=False)
        times, poses = times[0], poses[0]
        if tracker.twin is not None:  # the start search restarted both hypotheses: the twin is in the basin too
            assert tracker.twin.recover is None
            times, poses = times[-1:], tracker.twin.pose.clone()
        tracker.close()
        t, te, re = errors(seq, times, poses)
        results[name] = (float(te[-1]), float(re[-1]))
    assert results["plain"][0] > 0.01 or results["plain"][1] > 5.0, results
    for name in ("start search", "twin"):
        assert results[name][0] <= 0.015 and results[name][1] <= 5.0, results
    assert [c[0] for c in truth_search] == [t0 + RECOVER.recover.start_after_us] * 2


@pytest.fixture(scope="module")
def seqdirs(seq, tmp_path_factory):
    """The sequence saved with the events of 0.1 s on removed (lost from about 0.15 s, no event to search in)."""
    d = tmp_path_factory.mktemp("recover")
    blackout(seq, GAP_US[0], 10 ** 9).save(d / "dark")
    seq.save(d / "clean")
    return d


def test_track_recovers_by_default_and_writes_the_lost_flags_the_tracker_reports(seq, seqdirs, tmp_path,
                                                                                   capsys):
    out = tmp_path / "poses.txt"
    assert main(["track", str(seqdirs / "dark"), "--out", str(out), "--duration", "0.3", "--quiet"]) == 0
    t_file, poses_file = read_tum(out)
    t_lost, lost_file = read_lost(lost_path(out))
    assert lost_path(out).name == "poses.lost.txt"
    assert torch.equal(t_lost, t_file)
    dark = Sequence.load(seqdirs / "dark")  # camera, start pose and mesh as the command reads them
    t0 = int(dark.gt_t_us[0])
    tracker = EventPoseTracker(dark.camera, str(seqdirs / "dark" / "mesh.ply"), RECOVER)
    times, poses, lost = tracker.track(dark.events, dark.gt_poses[0], t_start_us=t0, t_end_us=t0 + 300_000,
                                       progress=False, return_lost=True)
    tracker.close()
    assert torch.equal(lost_file, lost[0])
    assert torch.allclose(poses_file, poses[0], atol=1e-8)  # the pose file's digits
    assert 50 < int(lost_file.sum()) < len(lost_file) and lost_file[-1]  # lost to the end: no events to search in
    assert "warning: the object was lost" in capsys.readouterr().err
    plain = tmp_path / "plain.txt"  # --no-recover: the config as given, no detector, no flags
    assert main(["track", str(seqdirs / "dark"), "--out", str(plain), "--no-recover", "--duration", "0.3",
                 "--quiet"]) == 0
    assert plain.exists() and not lost_path(plain).exists()


def test_a_wrong_init_is_moved_onto_the_object_or_flagged_lost(seq, seqdirs, tmp_path, capsys):
    """``track --recover`` from an init 16 cm (ADD-S) from the object (in view, near the optical axis): at the end the
    pose is within 5 cm of the object (ADD-S: up to the box's symmetries; the start search and the re-localiser
    restart it there) and not flagged lost, or the run ends flagged lost with a warning.

    Not "within 3 cm": of eight inits within 2 cm / 2 deg of this one, one ends 4.0 cm off and unflagged on one of
    two code generations (with one event per model edge in the search's window, two or three of eight ended 3.3-3.4
    cm off, 7 cm too deep, on both; docs/notebook.md, 2026-12-07 morning)."""
    out = tmp_path / "poses.txt"
    init = "0.22 -0.1 0.6 0.5 0.5 0.5 0.5"
    assert main(["track", str(seqdirs / "clean"), "--out", str(out), "--recover", "--duration", "0.3", "--init", init,
                 "--set", "recover.retry_us=100000", "--quiet"]) == 0
    warned = "warning: the object was lost" in capsys.readouterr().err
    t, poses = read_tum(out)
    _, lost = read_lost(lost_path(out))
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, t[[0, -1]])
    points = mesh_points(seq.mesh.vertices)
    assert float(adds_error(poses[:1], truth[:1], points)[0]) > 0.15  # the start is far off
    found = float(adds_error(poses[-1:], truth[1:], points)[0]) < 0.05
    assert (found and not lost[-1]) or (warned and lost[-1] and lost.sum() > 5), (found, warned)


@pytest.mark.parametrize("cost, own_cost, restarts", [(3.5, 9.0, 1), (1.0, 1.2, 0), (1.0, 1.8, 0), (1.0, 2.05, 1)])
def test_a_start_search_restarts_where_it_beats_the_trackers_pose(seq, monkeypatch, cost, own_cost, restarts):
    """A start search restarts where the result beats the tracker's own pose by ``START_MARGIN_PX`` (1 px), whatever
    its cost (3.5 px is above the lost element's clear-winner cost); a result less than 1 px better than the tracker's
    pose (0.2, 0.8 px), clear or not, leaves the element where it is."""
    def search(self, pose, last_us, t_now_us, own=None):
        found = interpolate_poses(seq.gt_t_us, seq.gt_poses, t_now_us)
        f64 = dict(dtype=torch.float64)
        return Relocalisation(found, torch.full((1,), cost, **f64), torch.full((1,), math.inf, **f64),
                              torch.tensor([cost <= CAP]), torch.full((1,), own_cost, **f64))

    monkeypatch.setattr(Relocaliser, "forward", search)
    monkeypatch.setattr(recover, "TURN_MARGIN", math.inf)  # (the turned poses never restart here: the next test)
    t0 = int(seq.gt_t_us[0])
    tracker = EventPoseTracker(CAM, seq.mesh, RECOVER.replace(recover={"start_search": True}))
    start = perturb_pose(seq.gt_poses[0], 0.02, math.radians(10.0), torch.Generator().manual_seed(5))
    end = t0 + RECOVER.recover.start_after_us + 10_000
    tracker.track(seq.events, start, t_start_us=t0, t_end_us=end, progress=False)
    tracker.close()
    assert tracker.recover.searches == 1 and tracker.recover.restarts == restarts


@pytest.mark.parametrize("gain, restarts", [(1.5, 1), (0.5, 0), (-3.0, 0)])
def test_a_start_search_turns_the_trackers_pose_where_the_chamfer_result_does_not_beat_it(seq, monkeypatch, gain,
                                                                                          restarts):
    """Where the chamfer result does not beat the tracker's pose, the tracker's pose turned (:func:`turned_poses`) and
    refined by the template (:meth:`EventPoseTracker.refine`, an oracle here that scores the tracker's own pose 10 and
    the fifth turned pose ``10 + gain``) restarts the element at that refined pose if it scores ``TURN_MARGIN`` (10 %)
    more: 15 % does, 5 % does not."""
    def search(self, pose, last_us, t_now_us, own=None):
        f64 = dict(dtype=torch.float64)
        return Relocalisation(own.clone(), torch.full((1,), 2.0, **f64), torch.full((1,), math.inf, **f64),
                              torch.ones(1, dtype=torch.bool), torch.full((1,), 2.0, **f64))

    calls = []

    def refine(self, poses, index, t_us, rounds=2):
        calls.append((poses.clone(), self.pose[index].clone()))
        score = torch.full((len(poses),), 9.0, dtype=torch.float64)
        score[0], score[5] = 10.0, 10.0 + gain
        return poses + torch.tensor([0.001, 0, 0, 0, 0, 0, 0]), score  # "refined": moved 1 mm along x

    monkeypatch.setattr(Relocaliser, "forward", search)
    monkeypatch.setattr(EventPoseTracker, "refine", refine)
    t0 = int(seq.gt_t_us[0])
    tracker = EventPoseTracker(CAM, seq.mesh, RECOVER.replace(recover={"start_search": True}))
    start = perturb_pose(seq.gt_poses[0], 0.02, math.radians(10.0), torch.Generator().manual_seed(5))
    at = t0 + RECOVER.recover.start_after_us
    reset = []
    real_reset = EventPoseTracker.reset
    monkeypatch.setattr(EventPoseTracker, "reset", lambda self, pose, twist=None, mask=None: (
        reset.append(pose.clone()), real_reset(self, pose, twist, mask))[1])
    tracker.track(seq.events, start, t_start_us=t0, t_end_us=at + 10_000, progress=False)
    tracker.close()
    (poses, own), = calls  # one start search
    assert torch.equal(poses, turned_poses(own, recover.TURN_DEG))
    assert tracker.recover.restarts == restarts
    if restarts:  # the restart pose is the refined fifth candidate
        assert torch.allclose(reset[-1][0], poses[5] + torch.tensor([0.001, 0, 0, 0, 0, 0, 0]), atol=1e-9)


def test_turned_poses_turn_about_each_camera_axis_through_the_object():
    pose = perturb_pose(torch.tensor([0.1, -0.05, 0.6, 1.0, 0.0, 0.0, 0.0]), 0.0, 0.7, torch.Generator().manual_seed(1))
    out = turned_poses(pose, (10.0, 20.0))
    assert out.shape == (13, 7) and torch.equal(out[0], pose.double())
    R0 = quat_to_matrix(pose.double()[3:])
    k = 1
    for axis in range(3):
        for deg in (10.0, 20.0):
            for sign in (1.0, -1.0):  # the camera-frame rotation about ``axis``, applied on the left
                a = math.radians(sign * deg)
                c, s_ = math.cos(a), math.sin(a)
                i, j = [(1, 2), (2, 0), (0, 1)][axis]
                Ra = torch.eye(3, dtype=torch.float64)
                Ra[i, i], Ra[i, j], Ra[j, i], Ra[j, j] = c, -s_, s_, c
                assert torch.allclose(quat_to_matrix(out[k, 3:]), Ra @ R0, atol=1e-12)
                assert torch.equal(out[k, :3], pose.double()[:3])
                k += 1


def test_refine_scores_poses_against_the_observation_and_leaves_the_tracker_as_it_was(seq):
    """``refine`` with no rounds returns the poses as given; an object out of view scores ``-inf`` and is not moved;
    a pose in view scores a finite, positive score (edges seen) and moves with rounds; the tracker's state stays."""
    t0 = int(seq.gt_t_us[0])
    t = t0 + 60_000
    tracker = EventPoseTracker(CAM, seq.mesh)
    tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t, progress=False)
    before = copy.deepcopy(tracker.state_dict())
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t]))[0]
    away = truth.clone()
    away[0] = 5.0  # far beside the view
    poses = torch.stack([truth, away])
    same, score0 = tracker.refine(poses, 0, t, rounds=0)
    moved, score2 = tracker.refine(poses, 0, t, rounds=2)
    assert torch.equal(same, poses) and torch.equal(moved[1], away)
    assert score0[0] > 0 and math.isfinite(score2[0]) and score0[1] == score2[1] == -math.inf
    assert not torch.equal(moved[0], truth)
    after = tracker.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    tracker.close()


def test_refine_scores_as_a_render_of_the_whole_frame_would(seq):
    """``refine`` renders each pose in a window around it, as updates do; its score (no rounds) is the one of an
    independent full-frame render of the pose made into a template model and scored against the same observation,
    for the truth and a pose 5 mm beside it."""
    t0 = int(seq.gt_t_us[0])
    t = t0 + 60_000
    tracker = EventPoseTracker(CAM, seq.mesh)
    tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t, progress=False)
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t]))[0].double()
    beside = truth.clone()
    beside[0] += 0.005
    poses = torch.stack([truth, beside])
    _, score = tracker.refine(poses, 0, t, rounds=0)
    renderer = RasterRenderer(seq.mesh, CAM)
    last = tracker.last_event_us[0:1]
    last = last[:, None] if last.ndim == 3 else last
    for k in range(2):
        full = renderer.render(poses[k:k + 1].float())
        model = tracker.corrector.template_model(poses[k:k + 1], full.depth, full.gray, (0, 0))
        canvas = model.depth.shape[-1]
        obs = canvas_observation(tracker.eros.surface[0:1], last, model.box, canvas, torch.tensor([t]),
                                 tracker.config.eros.max_age_us, tracker.recency.window_us[0:1]).reshape(1, -1)
        area = area_weight(obs[0].numpy(), model.valid[0].numpy(), canvas, float(model.interior[0]))
        expected = float(model.fit_canvas(obs).s0[0]) - area
        assert expected > 0 and float(score[k]) == pytest.approx(expected, rel=1e-4)
    renderer.close()
    tracker.close()


def test_recover_on_the_command_line_may_be_refined_by_set():
    """``--recover`` (track's default, benchmark's option) turns on the detector, recovery and the start search; --set
    refines it (``--set recover.start_search=false``)."""
    import argparse

    from torchevtrack.cli.options import config_from_args

    cfg = config_from_args(argparse.Namespace(config=None, set=None, recover=True))
    assert cfg.loss.enabled and cfg.recover.enabled and cfg.recover.start_search
    cfg = config_from_args(argparse.Namespace(config=None, set=["recover.start_search=false"], recover=True))
    assert cfg.loss.enabled and cfg.recover.enabled and not cfg.recover.start_search
    assert not config_from_args(argparse.Namespace(config=None, set=None, recover=False)).recover.enabled
    with pytest.raises(ValueError, match="needs recover.enabled"):
        config_from_args(argparse.Namespace(config=None, set=["recover.start_search=true"], recover=False))


@pytest.mark.parametrize("cost, own_cost, lost_after, restarts", [(0.9, 1.0, False, 0), (CAP + 0.8, CAP + 1.0, True, 0),
                                                                   (1.0, 3.0, False, 1)])
def test_a_search_confirms_restarts_or_keeps_looking_against_the_trackers_own_pose(seq, monkeypatch, cost, own_cost,
                                                                                    lost_after, restarts):
    """A false alarm (every update low: more flow vectors asked for than there are blocks) searched once: a result no
    better than the tracker's own pose, which costs at most ``max_cost_px``, confirms the pose (found again, no
    restart, the output unchanged); a pose above the cost keeps the element lost (the next search is a second away);
    a clear result that beats it restarts there."""
    def search(self, pose, last_us, t_now_us, own=None):
        f64 = dict(dtype=torch.float64)
        return Relocalisation(interpolate_poses(seq.gt_t_us, seq.gt_poses, t_now_us), torch.full((1,), cost, **f64),
                              torch.full((1,), math.inf, **f64), torch.tensor([cost <= CAP]),
                              torch.full((1,), own_cost, **f64))

    monkeypatch.setattr(Relocaliser, "forward", search)
    t0 = int(seq.gt_t_us[0])
    alarm = {"loss": {"enabled": True, "min_flow_vectors": 1000}}
    runs = {}
    for name, cfg in (("plain", TrackerConfig().replace(**alarm)),
                      ("recover", TrackerConfig().replace(**alarm, recover={"enabled": True, "retry_us": 10 ** 6}))):
        tracker = EventPoseTracker(CAM, seq.mesh, cfg)
        runs[name] = [v[0] for v in tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 100_000,
                                                  progress=False, return_lost=True)]
        tracker.close()
    assert runs["plain"][2][-1]  # the detector holds the element lost from about 50 ms to the end
    assert bool(runs["recover"][2][-1]) == lost_after
    if restarts:  # restarted, the detector starts over and declares the element lost again 50 ms later
        assert tracker.recover.restarts == tracker.recover.searches >= 1
    else:
        assert tracker.recover.searches == 1 and tracker.recover.restarts == 0
        assert torch.equal(runs["recover"][1], runs["plain"][1])


def track_searched(seq, monkeypatch, search, duration_us: int, **recover):
    """Track ``seq`` from its true start with every update low (more flow vectors asked for than there are blocks:
    lost 50 ms in) and the relocaliser's search replaced by ``search``; returns the closed tracker and the times
    (us) of the frame scans, which run as they are."""
    scans = []
    scan = Relocaliser.scan

    def record(self, pose, last_us, t_now_us):
        scans.append(int(t_now_us))
        return scan(self, pose, last_us, t_now_us)

    monkeypatch.setattr(Relocaliser, "forward", search)
    monkeypatch.setattr(Relocaliser, "scan", record)
    t0 = int(seq.gt_t_us[0])
    cfg = TrackerConfig().replace(loss={"enabled": True, "min_flow_vectors": 1000},
                                  recover={"enabled": True, **recover})
    tracker = EventPoseTracker(CAM, seq.mesh, cfg)
    tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + duration_us, progress=False)
    tracker.close()
    return tracker, scans


def test_searches_that_find_nothing_come_ever_further_apart(seq, monkeypatch):
    """A lost element whose searches find nothing (not clear, its own pose above the clear-winner cost) is searched
    at the declaration, then ``retry_us`` later, then at doubling intervals; each time around its last pose, then
    around the frame scan's candidate (the same update)."""
    calls = []

    def search(self, pose, last_us, t_now_us, own=None):
        calls.append(int(t_now_us[0]))
        f64 = dict(dtype=torch.float64)
        return Relocalisation(pose.clone(), torch.full((1,), 5.0, **f64), torch.full((1,), 5.1, **f64),
                              torch.tensor([False]), torch.full((1,), 5.2, **f64))

    tracker, scans = track_searched(seq, monkeypatch, search, 400_000)
    gaps = [b - a for a, b in zip(scans, scans[1:])]
    assert calls == [t for t in scans for _ in range(2)], (calls, scans)
    assert tracker.recover.searches == 5 and tracker.recover.restarts == 0 and bool(tracker.lost[0])
    assert gaps == [20_000, 40_000, 80_000, 160_000], gaps


@pytest.mark.parametrize("own_cost, restarts", [(5.5, 1), (6.5, 0)])
def test_a_search_that_finds_less_than_the_trackers_pose_searches_around_that_pose_next(seq, monkeypatch, own_cost,
                                                                                      restarts):
    """Where a lost element's search around its extrapolated last good pose finds nothing clear and costs more than
    the tracker's own pose, the next search is centred on the tracker's pose (which kept following the object while
    flagged), before any frame scan; a clear result there restarts the element. Where the tracker's pose costs more
    than that result, the scan comes next, as before."""
    calls = []

    def search(self, pose, last_us, t_now_us, own=None):
        calls.append(pose.clone())
        f64 = dict(dtype=torch.float64)
        if torch.equal(pose, own):  # centred on the tracker's pose: the truth there, clear
            return Relocalisation(interpolate_poses(seq.gt_t_us, seq.gt_poses, t_now_us),
                                  torch.full((1,), 1.0, **f64), torch.full((1,), math.inf, **f64),
                                  torch.tensor([True]), torch.full((1,), own_cost, **f64))
        return Relocalisation(pose.clone(), torch.full((1,), 6.0, **f64), torch.full((1,), 6.1, **f64),
                              torch.tensor([False]), torch.full((1,), own_cost, **f64))

    tracker, scans = track_searched(seq, monkeypatch, search, 100_000, retry_us=10 ** 6)
    centre = seq.gt_poses[:1]  # every update low: the good pose is the start pose, the good twist zero
    assert torch.equal(calls[0], centre.double())
    if restarts:  # the tracker's pose searched second and found, no scan; restarted, the element is declared again
        assert tracker.recover.restarts == tracker.recover.searches >= 1
        assert len(calls) == 2 * tracker.recover.searches and not torch.equal(calls[1], calls[0]) and scans == []
    else:  # the scan's candidate searched second
        assert tracker.recover.searches == 1 and tracker.recover.restarts == 0
        assert len(calls) == 2 and len(scans) == 1


def test_a_restart_needs_the_object_in_view_and_near_the_search_in_depth(seq):
    """A clear result that beats the tracker's pose restarts a lost element only with the object's centre in view
    and its depth within twice the search's depth reach of the search centre."""
    reloc = Relocaliser(RasterRenderer(seq.mesh, CAM), 0.1)
    centre = seq.gt_poses[:1].double()
    z = float(centre[0, 2])

    def result(pose, own=4.0):
        f64 = dict(dtype=torch.float64)
        return Relocalisation(pose, torch.ones(1, **f64), torch.full((1,), math.inf, **f64), torch.tensor([True]),
                              torch.full((1,), own, **f64))

    aside, deep = centre.clone(), centre.clone()
    aside[0, 0] += z * CAM.width / CAM.fx  # a frame's width to the side: out of view
    deep[0, :3] *= 1 + (2 * reloc.depth_reach_m + 0.01) / z  # along its line of sight: in view, too deep
    assert reloc.depth_reach_m == pytest.approx(0.1)
    assert found_again(result(centre), centre, reloc) and found_again(result(deep), deep, reloc)
    assert not found_again(result(aside), centre, reloc)
    assert not found_again(result(deep), centre, reloc)
    assert not found_again(result(centre, own=1.2), centre, reloc)  # no better than the tracker's own pose


def reference_bookkeeping(t, period_us, pose, declared, low_run, state, retry_us, start_after_us, check_us):
    """One update of the Recoverer's bookkeeping for one element, written from its module docstring; ``state`` a
    dict of python values and pose lists, updated in place. Returns ``(due, starting, checking)``."""
    if state["started"] < 0:
        state["started"] = state["good_us"] = state["anchor_us"] = t - period_us
        state["next_check"] = state["started"] + check_us
    if declared and not state["lost"]:
        state["lost"], state["next_search"], state["retry_in"] = True, t, retry_us
    if not state["lost"] and low_run == 0:
        state["good_pose"], state["good_us"] = list(pose), t
        if t - state["anchor_us"] >= TWIST_SPAN_US:
            state["twist"] = twist_between(torch.tensor([state["anchor_pose"]], dtype=torch.float64),
                                           torch.tensor([pose], dtype=torch.float64),
                                           (t - state["anchor_us"]) * 1e-6)[0].tolist()
            state["anchor_pose"], state["anchor_us"] = list(pose), t
    due = state["lost"] and t >= state["next_search"]
    starting = state["pending"] and not state["lost"] and t - state["started"] >= start_after_us
    if starting:
        state["pending"] = False
    checking = check_us > 0 and not state["lost"] and t >= state["next_check"]
    if checking:
        state["next_check"] = t + check_us
    return due, starting, checking


@pytest.mark.parametrize("seed", [0, 1])
def test_the_bookkeeping_kernel_matches_the_reference_per_element(seed):
    rng = np.random.default_rng(seed)
    B, T, period, retry, start_after, check = 3, 120, 2000, 20_000, 48_000, 30_000
    unit = [0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]
    buf = dict(lost=np.zeros(B, bool), good_pose=np.tile(unit, (B, 1)), good_us=np.zeros(B, np.int64),
               anchor_pose=np.tile(unit, (B, 1)), anchor_us=np.zeros(B, np.int64), twist=np.zeros((B, 6)),
               started=np.full(B, -1, np.int64), next_search=np.zeros(B, np.int64), retry_in=np.zeros(B, np.int64),
               pending=np.ones(B, bool), next_check=np.zeros(B, np.int64))
    refs = [dict(lost=False, good_pose=list(unit), good_us=0, anchor_pose=list(unit), anchor_us=0, twist=[0.0] * 6,
                 started=-1, next_search=0, retry_in=0, pending=True, next_check=0) for _ in range(B)]
    n = {"due": 0, "starting": 0, "twists": 0, "checking": 0}
    for i in range(T):
        t = np.full(B, period * (i + 1), np.int64)
        pose = np.tile(unit, (B, 1))
        pose[:, :3] += rng.normal(0.0, 0.01, (B, 3)) + 0.001 * i
        angle = 0.01 * i + rng.normal(0.0, 0.01, B)
        pose[:, 3], pose[:, 5] = np.cos(angle / 2), np.sin(angle / 2)
        declared = rng.random(B) < 0.03
        low_run = np.where(rng.random(B) < 0.3, rng.integers(1, 5, B), 0).astype(np.int64)
        due, starting, checking = np.zeros(B, bool), np.zeros(B, bool), np.zeros(B, bool)
        bookkeeping_kernel(t, period, pose, declared, low_run, buf["lost"], buf["good_pose"], buf["good_us"],
                           buf["anchor_pose"], buf["anchor_us"], buf["twist"], buf["started"], buf["next_search"],
                           buf["retry_in"], buf["pending"], retry, start_after, due, starting, buf["next_check"], check,
                           checking)
        for b in range(B):
            before = refs[b]["twist"]
            d, s, c = reference_bookkeeping(int(t[b]), period, pose[b].tolist(), bool(declared[b]), int(low_run[b]),
                                            refs[b], retry, start_after, check)
            n["twists"] += refs[b]["twist"] is not before
            assert (bool(due[b]), bool(starting[b]), bool(checking[b])) == (d, s, c), (i, b)
            for key, value in refs[b].items():
                assert np.allclose(buf[key][b], value, rtol=1e-12, atol=1e-12), (i, b, key)
            n["due"] += d
            n["starting"] += s
            n["checking"] += c
        if rng.random() < 0.05:  # a search confirmed an element's pose: found again
            k = int(rng.integers(B))
            buf["lost"][k] = refs[k]["lost"] = False
    assert n["due"] > 0 and n["starting"] > 0 and n["twists"] > 0 and n["checking"] > 0  # every branch taken


def test_the_recoverers_views_follow_copies_and_new_storage(seq):
    """The recoverer's bookkeeping kernel updates its buffers through numpy views: a deep copy of the tracker, or its
    buffers moved to new storage (``share_memory``), must be the ones updated."""
    t0 = int(seq.gt_t_us[0])
    tracker = EventPoseTracker(CAM, seq.mesh, RECOVER)
    tracker.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 20_000, progress=False)
    twin = copy.deepcopy(tracker)
    tracker.recover.share_memory()
    for tr in (tracker, twin):
        tr.track(seq.events, seq.gt_poses[0], t_start_us=t0, t_end_us=t0 + 40_000, progress=False)
        tr.close()
        assert not bool(tr.lost[0]) and int(tr.loss.low_run[0]) == 0
        assert int(tr.recover.good_us[0]) == t0 + 40_000  # the last window's end
        assert torch.equal(tr.recover.good_pose[0], tr.pose[0])


def test_a_batch_searches_the_same_events_with_and_without_the_pipeline(seq):
    # the search reads the time surface of the events up to its update: with one worker the pipeline's thread must
    # not be taking the next window in meanwhile (the real relocaliser: its result depends on every recent pixel)
    cfg = RECOVER.replace(recover={"start_search": True, "start_after_us": 30_000})
    g = torch.Generator().manual_seed(6)
    starts = torch.stack([perturb_pose(seq.gt_poses[0], 0.02, math.radians(10.0), g) for _ in range(2)])
    t0 = int(seq.gt_t_us[0])
    runs = []
    for pipeline in (False, True):
        tracker = EventPoseTracker(CAM, [seq.mesh] * 2, cfg, workers=1, pipeline=pipeline)
        poses = tracker.track([seq.events] * 2, starts, t_start_us=t0, t_end_us=t0 + 80_000, progress=False)[1]
        assert tracker.pipelined == pipeline and tracker.recover.searches == 2
        runs.append(poses)
        tracker.close()
    assert torch.equal(runs[0], runs[1])


@pytest.mark.parametrize("seed", [0, 1])
def test_the_fused_watch_gives_the_stage_calls_numbers(seed):
    """`update.watch` (the tracker's one compiled call after an update) against the loss detector's own forward, then
    the bookkeeping kernel with its verdict, then the search rule of the module docstring, one after the other."""
    from torchevtrack.loss import LossDetector
    from torchevtrack.recover import RecoverArrays
    from torchevtrack.tracker import Quality
    from torchevtrack.update import watch

    rng = np.random.default_rng(seed)
    B, T, period, retry, start_after, patience, check = 3, 200, 2000, 20_000, 48_000, 6, 50_000
    unit = [0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]

    def books():
        return [np.zeros(B, bool), np.tile(unit, (B, 1)), np.zeros(B, np.int64), np.tile(unit, (B, 1)),
                np.zeros(B, np.int64), np.zeros((B, 6)), np.full(B, -1, np.int64), np.zeros(B, np.int64),
                np.zeros(B, np.int64), np.ones(B, bool), np.zeros(B, np.int64)]

    dets = [LossDetector(B, score_threshold=0.3, patience=patience, recovery=4) for _ in range(2)]
    ref, fused = books(), books()
    outs = [np.zeros(B, bool), np.zeros(B, bool), np.zeros(B, bool), np.ones(1, bool)]
    n = {"newly": 0, "search": 0, "may": 0}
    for i in range(T):
        t = np.full(B, period * (i + 1), np.int64)
        pose = np.tile(unit, (B, 1))
        pose[:, :3] += rng.normal(0.0, 0.01, (B, 3))
        score = np.where(rng.random(B) < 0.1, np.nan, rng.gamma(2.0, 1.0 if (i // 40) % 2 == 0 else 0.1, B))
        score = score.astype(np.float32)  # as the tracker's
        flow_vectors = rng.integers(0, 8, B)
        rejected, burst = rng.random(B) < 0.05, rng.random(B) < 0.05
        upd = dets[0](Quality(torch.from_numpy(score), torch.from_numpy(flow_vectors), torch.zeros(B, dtype=torch.int64),
                              torch.from_numpy(rejected), torch.from_numpy(burst)), torch.from_numpy(t))
        due, starting, checking = np.zeros(B, bool), np.zeros(B, bool), np.zeros(B, bool)
        bookkeeping_kernel(t, period, pose, upd.newly_lost.numpy(), dets[0].low_run.numpy(), *ref[:10], retry,
                           start_after, due, starting, ref[10], check, checking)
        may = ref[0].any() or ref[9].any() or (dets[0].low_run.numpy() >= patience - 1).any() \
            or (t + period >= ref[10]).any()
        newly, search = watch(dets[1].arrays(), RecoverArrays(*fused, retry, start_after, check, *outs), score,
                              flow_vectors, rejected, burst, t, period, pose)
        assert newly == bool(upd.newly_lost.any()) and search == bool((due | starting | checking).any()), i
        assert np.array_equal(outs[0], due) and np.array_equal(outs[1], starting) \
            and np.array_equal(outs[2], checking) and outs[3][0] == may, i
        for a, b in zip(ref, fused):
            assert np.array_equal(a, b), i
        for name, buf in dets[0].named_buffers():
            torch.testing.assert_close(buf, getattr(dets[1], name), rtol=0, atol=0, equal_nan=True)
        n["newly"] += newly
        n["search"] += search
        n["may"] += may
    assert n["newly"] > 0 and n["search"] > 0 and 0 < n["may"] < T  # every branch taken
