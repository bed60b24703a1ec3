"""The burst guard inside the tracker: a 2 ms flash (every pixel firing) is dropped before any stage, costs an
update what an empty window does and leaves the pose on track; ordinary fast motion is never flagged."""

import math
import time
import tracemalloc

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.config import TrackerConfig
from torchevtrack.events import EventStream
from torchevtrack.loss import LossDetector
from torchevtrack.metrics import per_pose_errors
from torchevtrack.online import OnlineTracker
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.tracker import EventPoseTracker, Quality

CAM = Camera(320, 240, 251.15, 251.15, 159.5, 119.5)
FLASH_AT_S = 0.1  # after the first pose, plus 1 ms: the flash spans two 2 ms windows
AFTER_S = 0.2  # the error is compared this long after the flash


@pytest.fixture(scope="module")
def seq():
    return generate_sequence("box", "regular", 0.36, seed=3, camera=CAM, progress=False)


def with_flash(ev: EventStream, t_us: int, per_pixel: int = 4, seed: int = 0) -> EventStream:
    """``ev`` with a 2 ms flash merged in: every pixel fires ``per_pixel`` times at uniform random times in
    ``[t_us, t_us + 2000)``, random polarity."""
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(CAM.height), torch.arange(CAM.width), indexing="ij")
    x, y = xx.reshape(-1).repeat(per_pixel), yy.reshape(-1).repeat(per_pixel)
    t = t_us + torch.randint(0, 2000, (x.numel(),), generator=gen)
    p = torch.randint(0, 2, (x.numel(),), generator=gen)
    tt = torch.cat((ev.t, t))
    order = torch.argsort(tt, stable=True)
    cat = lambda a, b: torch.cat((a, b.to(a.dtype)))[order]  # noqa: E731
    return EventStream(cat(ev.x, x), cat(ev.y, y), tt[order], cat(ev.p, p))


def run(seq, events: EventStream, config: TrackerConfig | None = None, pipeline: bool | None = None):
    """Track update by update as :meth:`EventPoseTracker.track` does (the next window given ahead): update times,
    poses, burst flags, update milliseconds and the tracemalloc peak (bytes) of the loop."""
    tracker = EventPoseTracker(CAM, seq.mesh, config, pipeline=pipeline)
    t0, period = int(seq.gt_t_us[0]), tracker.period_us
    n = (int(seq.gt_t_us[-1]) - t0) // period
    bounds = torch.searchsorted(events.t, t0 + torch.arange(n + 1) * period).tolist()

    def window(i):
        if i >= n:
            return None
        w = events[bounds[i]:bounds[i + 1]]
        return w.x, w.y, w.t, w.p, None

    tracker.reset(seq.gt_poses[0])
    times = t0 + torch.arange(1, n + 1) * period
    poses, burst, ms = torch.empty(n, 7, dtype=torch.float64), torch.zeros(n, dtype=torch.bool), []
    ahead = window(0)
    tracemalloc.start()
    for i in range(n):
        current, ahead = ahead, window(i + 1)
        start = time.perf_counter()
        poses[i] = tracker(*current, t_us=int(times[i]), next_window=ahead)[0]
        ms.append((time.perf_counter() - start) * 1e3)
        q = tracker.quality
        burst[i] = bool(q.burst[0]) if q.burst is not None else False
    tracker.close()  # first: the pipeline thread may still allocate, and stopping tracemalloc under it can crash
    peak = tracemalloc.get_traced_memory()[1]  # CPython 3.11
    tracemalloc.stop()
    return times, poses, burst, ms, peak


def error_at(seq, times, poses, t_us):
    """Translation (m) and rotation (deg) error of the first update at or after ``t_us``."""
    i = int(torch.searchsorted(times, t_us))
    e = per_pose_errors(times[i:i + 1], poses[i:i + 1], seq.gt_t_us, seq.gt_poses)
    return float(e["te"][0]), math.degrees(float(e["re"][0]))


@pytest.fixture(scope="module")
def flash_runs(seq):
    t_flash = int(seq.gt_t_us[0]) + round(FLASH_AT_S * 1e6) + 1000
    flashed = with_flash(seq.events, t_flash)
    return t_flash, flashed, run(seq, seq.events), run(seq, flashed)


def test_a_flash_is_dropped_and_the_pose_stays_on_track(seq, flash_runs):
    t_flash, flashed, (times, clean, flags0, ms0, peak0), (_, poses, flags, ms, peak) = flash_runs
    hit = ((times > t_flash) & (times - 2000 < t_flash + 2000)).nonzero()[:, 0]  # the windows the flash falls in
    assert not flags0.any()
    assert flags.nonzero()[:, 0].tolist() == hit.tolist() and len(hit) == 2
    t_after = t_flash + round(AFTER_S * 1e6)
    e0, e1 = error_at(seq, times, clean, t_after), error_at(seq, times, poses, t_after)
    print(f"\nflash of {len(flashed) - len(seq.events)} events: flash updates {[round(ms[i], 1) for i in hit]} ms, "
          f"longest update {max(ms[5:]):.1f} ms (without the flash {max(ms0[5:]):.1f}); tracemalloc peak "
          f"{peak / 1e6:.1f} MB (without {peak0 / 1e6:.1f}); error {AFTER_S} s later {e1[0] * 100:.3f} cm / "
          f"{e1[1]:.2f} deg (without {e0[0] * 100:.3f} cm / {e0[1]:.2f} deg)")
    assert abs(e1[0] - e0[0]) < 0.01 and abs(e1[1] - e0[1]) < 5.0
    assert peak < 1.2 * peak0 + 1e6
    # before the flash the two runs are the same run
    before = times < t_flash
    assert torch.equal(poses[before], clean[before])


def test_a_flash_judged_ahead_gives_the_serial_poses(seq, flash_runs):
    # without render.ahead the pipeline takes the next window in during an update: the guard judges it then
    t_flash, flashed, _, _ = flash_runs
    cfg = TrackerConfig().replace(render={"ahead": False})
    _, ahead, flags, _, _ = run(seq, flashed, cfg, pipeline=True)
    _, serial, flags_serial, _, _ = run(seq, flashed, cfg, pipeline=False)
    assert flags.sum() == 2 and torch.equal(flags, flags_serial)
    assert torch.equal(ahead, serial)


def test_online_pushes_drop_the_flash_as_the_offline_loop_does(seq, flash_runs):
    t_flash, flashed, _, (times, poses, _, _, _) = flash_runs
    t0 = int(seq.gt_t_us[0])
    stop = t_flash + 20_000
    tracker = EventPoseTracker(CAM, seq.mesh)
    online = OnlineTracker(tracker)
    online.start(seq.gt_poses[0], t0)
    out = []
    bounds = torch.searchsorted(flashed.t, torch.arange(t0, stop, 5000)).tolist()
    for i, j in zip(bounds[:-1], bounds[1:]):  # 5 ms pushes: several windows per push, the next one known ahead
        out += online.push(flashed[i:j])
    tracker.close()
    k = len(out)
    assert times[k - 1] > t_flash + 4000  # past the flash
    assert [t for t, _ in out] == times[:k].tolist()
    assert torch.equal(torch.stack([p[0] for _, p in out]), poses[:k])


def test_without_the_guard_the_flash_reaches_the_stages(seq):
    t_flash = int(seq.gt_t_us[0]) + round(FLASH_AT_S * 1e6) + 1000
    off = TrackerConfig().replace(burst={"enabled": False})
    times, clean, _, _, _ = run(seq, seq.events, off)
    _, poses, flags, _, _ = run(seq, with_flash(seq.events, t_flash), off)
    assert not flags.any()  # no guard, no flags
    after = times > t_flash + 2000
    assert not torch.equal(poses[after], clean[after])  # the flash changed the run (what the guard prevents)


def test_fast_motion_is_never_flagged_and_costs_nothing():
    fast = generate_sequence("box", "fast", 0.2, seed=3, camera=CAM, progress=False)
    times, on, flags, ms_on, _ = run(fast, fast.events)
    _, off, _, ms_off, _ = run(fast, fast.events, TrackerConfig().replace(burst={"enabled": False}))
    assert not flags.any()
    assert torch.equal(on, off)
    ms_on, ms_off = sorted(ms_on[10:]), sorted(ms_off[10:])
    print(f"\nmedian update with the guard {ms_on[len(ms_on) // 2]:.3f} ms, without {ms_off[len(ms_off) // 2]:.3f} ms")


def test_a_burst_update_is_neutral_for_the_loss_detector():
    det = LossDetector(2, patience=2, recovery=1)
    low = Quality(torch.tensor([0.0, 0.0]), torch.tensor([0, 0]), torch.tensor([10, 10]), torch.tensor([False, False]))
    det(Quality(torch.tensor([1.0, 1.0]), torch.tensor([9, 9]), torch.tensor([10, 10]), torch.tensor([False, False])),
        0)
    det(low, 1)
    before = {k: v.clone() for k, v in det.state_dict().items()}
    upd = det(Quality(low.score, low.flow_vectors, low.events, low.rejected, torch.tensor([True, False])), 2)
    # element 0 (burst) keeps its state; element 1 (a second low update) is declared lost
    assert upd.lost.tolist() == [False, True]
    for k, v in det.state_dict().items():
        if v.ndim:
            assert torch.equal(v[0], before[k][0]), k
