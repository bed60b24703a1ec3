"""The denoise stage inside the tracker: its output equals tracking the events the stage itself kept."""

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.stages.denoise import BackgroundActivityFilter
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)


@pytest.fixture(scope="module")
def noisy():
    seq = generate_sequence("box", "regular", 0.12, seed=3, camera=CAM, progress=False)
    ev, gen = seq.events, torch.Generator().manual_seed(1)
    n = int(5.0 * CAM.width * CAM.height * (int(ev.t[-1]) - int(ev.t[0])) * 1e-6)  # 5 Hz per pixel
    t = torch.randint(int(ev.t[0]), int(ev.t[-1]), (n,), generator=gen)
    tt = torch.cat((ev.t, t))
    order = torch.argsort(tt, stable=True)
    cat = lambda a, b: torch.cat((a, b.to(a.dtype)))[order]  # noqa: E731
    noise = (torch.randint(0, CAM.width, (n,), generator=gen), torch.randint(0, CAM.height, (n,), generator=gen),
             torch.randint(0, 2, (n,), generator=gen))
    return seq, EventStream(cat(ev.x, noise[0]), cat(ev.y, noise[1]), tt[order], cat(ev.p, noise[2]))


def _track(seq, events, config):
    tracker = EventPoseTracker(CAM, seq.mesh, config)
    times, poses = tracker.track(events, seq.gt_poses[0], t_start_us=int(seq.gt_t_us[0]),
                                 t_end_us=int(seq.gt_t_us[-1]), progress=False)
    tracker.close()
    return times, poses


def test_denoise_in_the_tracker_equals_tracking_the_prefiltered_events(noisy):
    seq, events = noisy
    on = TrackerConfig().replace(denoise={"enabled": True})
    keep = BackgroundActivityFilter(CAM.height, CAM.width, dt_us=on.denoise.dt_us)(events.x, events.y, events.t)
    assert 0.05 < 1 - keep.float().mean() < 0.9  # the filter drops part of the stream
    kept = EventStream(events.x[keep], events.y[keep], events.t[keep], events.p[keep])
    t1, p1 = _track(seq, events, on)
    t2, p2 = _track(seq, kept, TrackerConfig())
    t3, p3 = _track(seq, events, TrackerConfig())
    assert torch.equal(t1, t2) and torch.equal(p1, p2)
    assert not torch.equal(p1, p3)  # the stage changed what the tracker saw
