"""``torchevtrack live``: a dv-processing NetworkWriter on loopback serves a synthetic sequence; the live command
tracks it as the offline tracker does. A recording played in real time stops cleanly on Ctrl-C (SIGINT) with every
pose written."""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

pytest.importorskip("dv_processing", reason="the live extra (dv-processing) is not installed")

from torchevtrack.camera import Camera  # noqa: E402
from torchevtrack.io.poses import read_tum  # noqa: E402
from torchevtrack.synth.generate import generate_sequence  # noqa: E402
from torchevtrack.synth.sequence import Sequence  # noqa: E402
from torchevtrack.tracker import EventPoseTracker  # noqa: E402

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)
ENV = {**os.environ, "PYTHONPATH": os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", "")}

WRITER = textwrap.dedent("""
    import os, sys, time
    import dv_processing as dv
    from torchevtrack.io.events_h5 import read_events_h5
    ev = read_events_h5(sys.argv[1])
    x, y, t, p = (f.numpy().tolist() for f in (ev.x, ev.y, ev.t, ev.p))
    stream = dv.io.Stream.EventStream(0, "events", "torchevtrack-test", (int(sys.argv[3]), int(sys.argv[4])))
    writer = dv.io.NetworkWriter("127.0.0.1", int(sys.argv[2]), stream)
    print("listening", flush=True)
    while writer.getClientCount() == 0:
        time.sleep(0.01)
    i = 0
    while i < len(t):  # packets of 1 ms of events, a little faster than real time
        j = i
        while j < len(t) and t[j] < t[i] + 1000:
            j += 1
        store = dv.EventStore()
        for k in range(i, j):
            store.push_back(t[k], x[k], y[k], bool(p[k]))
        writer.writeEvents(store)
        i = j
        time.sleep(0.0005)
    print("sent", flush=True)
    while True:  # the server stays up, as DV software does, until the test ends it
        time.sleep(1)
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def seqdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("live")
    generate_sequence("box", "regular", 0.3, seed=6, camera=CAM, progress=False).save(root / "seq")
    return root / "seq"


def _init(seq: Sequence) -> tuple[str, torch.Tensor]:
    p = seq.gt_poses[0]
    return " ".join(f"{v:.9f}" for v in (*p[:3].tolist(), *p[4:].tolist(), float(p[3]))), p


@pytest.fixture(scope="module")
def offline(seqdir):
    """The offline tracker from the first event's time, at the pose --init gives."""
    seq = Sequence.load(seqdir)
    text, _ = _init(seq)
    from torchevtrack.cli.track import parse_init

    tracker = EventPoseTracker(CAM, seqdir / "mesh.ply")
    t_us, poses = tracker.track(seq.events, parse_init(text), t_start_us=seq.events.t_start, progress=False)
    tracker.close()
    return t_us[0], poses[0]


def _live(seqdir, source: str, out, *extra) -> subprocess.Popen:
    text, _ = _init(Sequence.load(seqdir))
    return subprocess.Popen([sys.executable, "-m", "torchevtrack", "live", source, "--camera",
                             str(seqdir / "camera.json"), "--mesh", str(seqdir / "mesh.ply"), "--init", text, "--out",
                             str(out), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


def test_live_over_loopback_tracks_as_offline(seqdir, offline, tmp_path):
    t_off, p_off = offline
    port = _free_port()
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(seqdir / "events.h5"), str(port), "160", "120"],
                              stdout=subprocess.PIPE, text=True, env=ENV)
    live = None
    try:
        assert writer.stdout.readline().strip() == "listening"
        out = tmp_path / "live.txt"
        live = _live(seqdir, f"tcp://127.0.0.1:{port}", out)
        assert live.stdout.readline().startswith("live: tracking")
        assert writer.stdout.readline().strip() == "sent"
        lines, deadline = [], time.monotonic() + 120
        while not lines or not lines[-1].startswith(f"live: {len(t_off)} poses"):  # a status line a second
            lines.append(live.stdout.readline())
            assert lines[-1] and time.monotonic() < deadline, "".join(lines)
        live.send_signal(signal.SIGINT)  # the stream stays open: the user stops the run
        stdout, stderr = live.communicate(timeout=60)
    finally:
        writer.kill()
        if live is not None:
            live.kill()
    assert live.returncode == 0, stderr
    printed = "".join(lines) + stdout
    assert f"stopped (Ctrl-C): {len(t_off)} poses" in printed and "late 0, dropped 0" in printed
    t_us, poses = read_tum(out)
    assert torch.equal(t_us, t_off)  # every window of the stream, stamped as offline
    assert float((poses[:, :3] - p_off[:, :3]).norm(dim=-1).max()) < 0.01  # within 1 cm of the offline poses
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]


def test_ctrl_c_stops_a_realtime_playback_with_every_pose_written(seqdir, offline, tmp_path):
    out = tmp_path / "live.txt"
    proc = _live(seqdir, str(seqdir / "events.h5"), out, "--realtime")
    try:
        assert proc.stdout.readline().startswith("live: tracking")
        time.sleep(0.15)  # part of the 0.3 s recording
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, stderr
    assert "stopped (Ctrl-C)" in stdout
    n = int(stdout.split("stopped (Ctrl-C): ")[1].split()[0])
    t_us, poses = read_tum(out)
    t_off, p_off = offline
    assert 0 < n == len(t_us) < len(t_off)  # stopped part-way, every pose it made is in the file
    assert torch.equal(t_us, t_off[:n])
    assert float((poses[:, :3] - p_off[:n, :3]).norm(dim=-1).max()) < 0.01


def test_runner_drops_late_and_off_sensor_events_and_counts_them(seqdir, offline):
    from torchevtrack.cli.track import parse_init
    from torchevtrack.events import EventStream
    from torchevtrack.live import LiveRunner
    from torchevtrack.online import OnlineTracker

    seq = Sequence.load(seqdir)
    tracker = EventPoseTracker(CAM, seqdir / "mesh.ply")
    runner = LiveRunner(OnlineTracker(tracker), parse_init(_init(seq)[0]))
    ev = seq.events
    cuts = np.linspace(0, len(ev), 40).astype(int)
    assert runner.feed(None) == [] and runner.trajectory()[0].numel() == 0  # nothing arrived yet
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        chunk = ev[int(a):int(b)]
        if k == 10:  # an event from the past (late) and one outside the sensor, inside an otherwise good chunk
            t_late, t_mid = int(ev.t[int(cuts[5])]), int(chunk.t[len(chunk) // 2])
            extra = EventStream.from_arrays(x=[3, CAM.width + 5], y=[4, 2], t=[t_late, t_mid], p=[1, 0],
                                            validate=False)
            chunk = EventStream.concat([chunk[:len(chunk) // 2], extra, chunk[len(chunk) // 2:]])
        runner.feed(chunk)
    tracker.close()
    status = runner.report()
    assert (status.late, status.dropped, status.events) == (1, 1, len(ev))
    t_us, poses = runner.trajectory()
    t_off, p_off = offline
    assert torch.equal(t_us, t_off) and status.poses == len(t_off)
    np.testing.assert_allclose(poses.numpy(), p_off.numpy(), atol=1e-9)  # as if the bad events never came


def test_a_recording_read_to_its_end_gives_the_offline_poses(seqdir, offline, tmp_path, capsys):
    from torchevtrack.cli import main

    out = tmp_path / "poses.txt"
    text, _ = _init(Sequence.load(seqdir))
    assert main(["live", str(seqdir / "events.h5"), "--camera", str(seqdir / "camera.json"), "--mesh",
                 str(seqdir / "mesh.ply"), "--init", text, "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    t_off, p_off = offline
    assert f"end of stream: {len(t_off)} poses, written to {out}" in printed
    t_us, poses = read_tum(out)
    assert torch.equal(t_us, t_off)
    assert float((poses[:, :3] - p_off[:, :3]).norm(dim=-1).max()) < 0.01
    with pytest.raises(SystemExit):
        main(["live", str(seqdir / "events.h5"), "--camera", str(seqdir / "camera.json"), "--mesh", "box"])
    assert "--init" in capsys.readouterr().err
    assert main(["live", "tcp://127.0.0.1", "--camera", str(seqdir / "camera.json"), "--mesh", "box", "--init",
                 text]) == 2
    assert "tcp://HOST:PORT" in capsys.readouterr().err
    assert main(["live", str(tmp_path / "missing.h5"), "--camera", str(seqdir / "camera.json"), "--mesh", "box",
                 "--init", text]) == 2
    assert "camera[:NAME] or an existing file" in capsys.readouterr().err


@pytest.mark.parametrize("ahead, pulled_first", [(100, 2), (10_000, 4)])
def test_realtime_playback_decodes_ahead_of_its_clock_and_gives_every_event(monkeypatch, ahead, pulled_first):
    """A paced recording is decoded (up to AHEAD_EVENTS) before its first event is given out, so that decoding does not
    share the tracker's time during the playback; all events come out, in order, in 1 ms pieces."""
    from torchevtrack import live
    from torchevtrack.events import EventStream

    chunks = [EventStream.from_arrays(x=np.arange(50) % CAM.width, y=np.full(50, 3), t=i * 5000 + np.arange(50) * 100,
                                      p=np.arange(50) % 2) for i in range(4)]  # 4 chunks of 50 events, 20 ms
    pulled = []

    def file():
        for c in chunks:
            pulled.append(len(c))
            yield c

    monkeypatch.setattr(live, "AHEAD_EVENTS", ahead)
    source = live._FileSource.__new__(live._FileSource)
    source.file, source.realtime = file(), True
    given = iter(source)
    first = next(given)  # the first 1 ms piece, or None while its time has not come
    assert len(pulled) == pulled_first  # 100 events: the first two chunks; 10,000: the whole file
    out = [c for c in (first, *given) if c is not None]
    assert all(len(c) and int(c.t[-1]) - int(c.t[0]) < 1000 for c in out)
    assert torch.equal(torch.cat([c.t for c in out]), torch.cat([c.t for c in chunks]))
    assert torch.equal(torch.cat([c.x for c in out]), torch.cat([c.x for c in chunks]))
