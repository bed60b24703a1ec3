"""Two hypotheses (torchevtrack.hypotheses): the arbitration rule against a per-element reference; a tracker that
adopts another's state goes on as that one does; a hypothesis knocked off the object is replaced by its twin, where
the tracker alone stays off."""

import math

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.geometry import interpolate_poses, perturb_pose
from torchevtrack.hypotheses import arbitrate
from torchevtrack.metrics import pose_errors
from torchevtrack.stages import NEVER
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
PERIOD_US = TrackerConfig().period_us


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.4, seed=3, camera=CAM, progress=False)


def reference_arbitrate(costs: list[tuple[float, float]], ratio: float, patience: int) -> list[int]:
    """The rule for one element, check by check, written from its description."""
    runs, out = [0, 0], []
    for c0, c1 in costs:
        runs = [runs[0] + 1 if c1 > ratio * c0 else 0, runs[1] + 1 if c0 > ratio * c1 else 0]
        winner = 0 if runs[0] >= patience else 1 if runs[1] >= patience else -1
        if winner >= 0:
            runs = [0, 0]
        out.append(winner)
    return out


@pytest.mark.parametrize("ratio, patience", [(1.25, 2), (1.1, 1), (1.5, 3)])
def test_arbitrate_matches_a_per_element_reference(ratio, patience):
    g = torch.Generator().manual_seed(patience)
    B, T = 12, 60
    costs = 1.0 + 2.0 * torch.rand(T, B, 2, generator=g, dtype=torch.float64)
    costs[:, :4, 1] = costs[:, :4, 0] * 1.3 * ratio  # elements 0-3: hypothesis 0 clearly better throughout
    run = torch.zeros(B, 2, dtype=torch.int64)
    got = torch.stack([arbitrate(costs[k], run, ratio, patience) for k in range(T)], 1)  # (B, T)
    for b in range(B):
        assert got[b].tolist() == reference_arbitrate(costs[:, b].tolist(), ratio, patience)
    assert (got[:4] == 0).sum(1).tolist() == [T // patience] * 4 and (got[4:] == 1).any() and (got == -1).any()


def test_costs_rank_the_truth_before_poses_off_it(seq):
    from torchevtrack.raster import RasterRenderer
    from torchevtrack.stages.relocalise import Relocaliser

    reloc = Relocaliser(RasterRenderer(seq.mesh, CAM), float(torch.as_tensor(seq.mesh.vertices).norm(dim=1).max()))
    t = int(seq.gt_t_us[0]) + 200_000
    ev = seq.events.slice_time(t - 30_000, t + 1)
    last = torch.full((CAM.height, CAM.width), NEVER, dtype=torch.int64)
    last[ev.y.long(), ev.x.long()] = ev.t  # the newest event per pixel (time order: the last write wins)
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t]))[0]
    g = torch.Generator().manual_seed(4)
    off = torch.stack([perturb_pose(truth, 0.03, math.radians(15), g) for _ in range(4)])
    costs = reloc.costs(torch.cat((truth[None], off)), last, t)
    assert costs.shape == (5,) and bool((costs[1:] > 1.25 * costs[0]).all()), costs.tolist()


def test_costs_are_the_two_sided_chamfer_cost_over_the_whole_frame(seq):
    # the oracle: the recent events and the pose's model edges as whole-frame images, chamfer() over them (costs
    # reads the events' distances only near the pose's window)
    from torchevtrack.chamfer import chamfer, distance_map, model_edges
    from torchevtrack.raster import RasterRenderer
    from torchevtrack.stages.relocalise import Relocaliser

    renderer = RasterRenderer(seq.mesh, CAM)
    reloc = Relocaliser(renderer, float(torch.as_tensor(seq.mesh.vertices).norm(dim=1).max()))
    t = int(seq.gt_t_us[0]) + 200_000
    ev = seq.events.slice_time(t - 30_000, t + 1)
    last = torch.full((CAM.height, CAM.width), NEVER, dtype=torch.int64)
    last[ev.y.long(), ev.x.long()] = ev.t
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t]))[0]
    g = torch.Generator().manual_seed(5)
    for pose in [truth] + [perturb_pose(truth, 0.02, math.radians(10), g) for _ in range(3)]:
        cost = float(reloc.costs(pose[None], last, t)[0])
        events = reloc._events(pose[None], last, t)  # costs' observation: recent pixels with a recent neighbour
        image = torch.zeros(CAM.height, CAM.width, dtype=torch.bool).numpy()
        image[events[:, 1], events[:, 0]] = True
        depth, gray = renderer.render_unit(pose[None].numpy(), CAM, shaded=True)
        edges = model_edges(depth, gray)[0]
        assert image.sum() > 100 and edges.sum() > 100 and not (edges[:4].any() or edges[-4:].any())
        assert cost == pytest.approx(chamfer(edges, image, distance_map(image, reloc.cap_px), reloc.cap_px), rel=1e-6)


def feed(trackers, seq, t0: int, n: int, start: int = 0) -> list[list[torch.Tensor]]:
    """Updates ``start .. start + n - 1`` (2 ms windows from ``t0``) given to each tracker; their outputs."""
    ev = seq.events
    out = [[] for _ in trackers]
    for i in range(start, start + n):
        w = ev.slice_time(t0 + i * PERIOD_US, t0 + (i + 1) * PERIOD_US)
        for k, tr in enumerate(trackers):
            out[k].append(tr(w.x, w.y, w.t, w.p, t_us=t0 + (i + 1) * PERIOD_US)[0])
    return out


def test_a_tracker_that_adopts_another_goes_on_as_that_one_does(seq):
    cfg = TrackerConfig().replace(ukf={"enabled": False})
    a, b, control = (EventPoseTracker(CAM, "box", cfg, pipeline=False) for _ in range(3))
    t0, gt0 = int(seq.gt_t_us[0]), seq.gt_poses[0]
    a.reset(gt0)
    control.reset(gt0)
    b.reset(perturb_pose(gt0, 0.01, math.radians(5), torch.Generator().manual_seed(1)))
    feed((a, b, control), seq, t0, 40)  # a and b now move differently
    a.adopt(b)
    assert torch.equal(a.pose, b.pose) and torch.equal(a.velocity.x, b.velocity.x)
    pa, pb, pc = (torch.stack(p) for p in feed((a, b, control), seq, t0, 40, start=40))
    assert torch.equal(pa, pb)  # after adopting, a continues exactly as b does, not as it would have (the control)
    assert float(pose_errors(pc, pb)["te"].max()) > 1e-3


def test_a_hypothesis_knocked_off_the_object_is_replaced_by_its_twin(seq):
    t0, gt0 = int(seq.gt_t_us[0]), seq.gt_poses[0]
    knock_at, n = 50, (int(seq.gt_t_us[-1]) - t0) // PERIOD_US  # knocked at 0.1 s
    truth = interpolate_poses(seq.gt_t_us, seq.gt_poses, t0 + PERIOD_US * torch.arange(1, n + 1))
    runs = {}
    for name, cfg in (("alone", TrackerConfig().replace(**ABLATIONS["full"])),
                      ("twin", TrackerConfig().replace(**ABLATIONS["hypotheses"])),
                      ("no_ukf", TrackerConfig().replace(ukf={"enabled": False}))):
        tracker = EventPoseTracker(CAM, "box", cfg, pipeline=False)
        tracker.reset(gt0)
        before = feed((tracker,), seq, t0, knock_at)[0]
        if name != "no_ukf":  # the tracker's own hypothesis (with the UKF) knocked 3 cm / 35 deg off; the twin not
            off = EventPoseTracker(CAM, "box", TrackerConfig(), pipeline=False)
            off.reset(perturb_pose(truth[knock_at - 1], 0.03, math.radians(35), torch.Generator().manual_seed(2)))
            tracker.adopt(off)
        runs[name] = (tracker, torch.stack(before + feed((tracker,), seq, t0, n - knock_at, start=knock_at)[0]))
    tracker, poses = runs["twin"]
    assert tracker.hypotheses.switches == 1 and int(tracker.hypotheses.chosen[0]) == 1
    assert tracker.twin.eros is tracker.eros and tracker.twin.flow is tracker.flow  # one intake for both
    # from the first check on (20 ms after the knock) the output is the twin's, which is the tracker without a UKF
    assert torch.equal(poses[knock_at + 10:], runs["no_ukf"][1][knock_at + 10:])
    alone = torch.rad2deg(pose_errors(runs["alone"][1][knock_at + 10:], truth[knock_at + 10:])["re"])
    chosen = torch.rad2deg(pose_errors(poses[knock_at + 10:], truth[knock_at + 10:])["re"])
    # without the twin the tracker is still off when the twin takes over, and comes back only slowly
    assert float(alone[0]) > 20.0 and float(alone.mean()) > 2.5 * float(chosen.mean()), (alone, chosen)


def test_a_batch_gives_the_same_poses_with_and_without_the_pipeline(seq):
    # the twin reads the tracker's event stages after the tracker's update, and a check reads the time surface of the
    # events up to its update: the pipeline's thread must take no window in ahead of them
    cfg = TrackerConfig().replace(**ABLATIONS["hypotheses"])
    g = torch.Generator().manual_seed(5)
    starts = torch.stack([seq.gt_poses[0], perturb_pose(seq.gt_poses[0], 0.02, math.radians(20), g)])
    runs = []
    for pipeline in (False, True):
        tracker = EventPoseTracker(CAM, ["box", "box"], cfg, workers=1, pipeline=pipeline)
        runs.append((tracker.track([seq.events] * 2, starts, progress=False)[1], tracker.hypotheses.costs.clone()))
        assert tracker.pipelined == pipeline and tracker.hypotheses.checks >= 2 * 15
        tracker.close()
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])  # the last checks' costs too


def test_hypotheses_need_the_ukf_and_the_template():
    with pytest.raises(ValueError, match="hypotheses.enabled needs ukf.enabled"):
        TrackerConfig().replace(hypotheses={"enabled": True}, ukf={"enabled": False})
    with pytest.raises(ValueError, match="hypotheses.ratio must be > 1"):
        TrackerConfig().replace(hypotheses={"ratio": 1.0})
