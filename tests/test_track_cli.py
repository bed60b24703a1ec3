"""``torchevtrack track`` reads any event format and undistorts the events of a camera with lens distortion.

Oracle: a pincushion model (``k1, k2 > 0``) stretches the image everywhere, so distorting a pinhole
pixel, rounding to the sensor grid, undistorting and rounding again returns the original pixel exactly.
The distorted recording, undistorted by the command, is then the pinhole recording itself (minus the
events the distortion pushed off the sensor): tracking must give the same poses, digit for digit.
"""

import dataclasses
import re
import shutil

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.cli.track import read_camera_events
from torchevtrack.distortion import distort_points, undistort_events
from torchevtrack.events import EventStream
from torchevtrack.io.events_h5 import read_events_h5, write_events_h5
from torchevtrack.synth.generate import generate_sequence

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)
PINCUSHION = (0.4, 0.1, 0.0, 0.0, 0.0)


def _distort(ev: EventStream, cam: Camera, coeffs) -> tuple[EventStream, torch.Tensor]:
    """Sensor events of pinhole events (nearest pixel) and which pinhole events stay on the sensor."""
    xy = torch.stack(((ev.x.double() - cam.cx) / cam.fx, (ev.y.double() - cam.cy) / cam.fy), -1)
    d = distort_points(xy, coeffs)
    u, v = (d[:, 0] * cam.fx + cam.cx).round(), (d[:, 1] * cam.fy + cam.cy).round()
    keep = (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
    return EventStream(u[keep].to(ev.x.dtype), v[keep].to(ev.y.dtype), ev.t[keep], ev.p[keep]), keep


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("distorted")
    seq = generate_sequence("box", "regular", 0.04, seed=5, camera=CAM, progress=False)
    distorted, keep = _distort(seq.events, CAM, PINCUSHION)
    assert int(keep.sum()) > 0.9 * len(keep)
    seq.events = seq.events.select(keep)
    seq.save(root / "pinhole")
    shutil.copytree(root / "pinhole", root / "distorted")
    write_events_h5(root / "distorted" / "events.h5", distorted, width=CAM.width, height=CAM.height)
    dataclasses.replace(CAM, distortion=PINCUSHION).save(root / "distorted" / "camera.json")
    return root


def test_track_undistorts_the_events_of_a_distorted_camera(dirs, capsys):
    cam = Camera.load(dirs / "distorted" / "camera.json")
    assert cam.distortion == PINCUSHION
    seen = read_camera_events(dirs / "distorted" / "events.h5", cam, chunk=777)  # what the command tracks
    pinhole = read_events_h5(dirs / "pinhole" / "events.h5")
    for f in "xytp":
        assert torch.equal(getattr(seen, f).long(), getattr(pinhole, f).long()), f
    assert "dropped 0" in capsys.readouterr().err
    runs = {}
    for name, src, extra in (("pinhole", "pinhole", []), ("undistorted", "distorted", []),
                             ("raw", "distorted", ["--no-undistort"])):
        out = dirs / f"{name}.txt"
        assert main(["track", str(dirs / src), "--out", str(out), "--quiet"] + extra) == 0
        runs[name] = out.read_text()
    assert runs["undistorted"] == runs["pinhole"]
    assert runs["raw"] != runs["pinhole"]  # the sensor pixels are up to ~4 px off near the object


def test_chunked_undistortion_equals_the_whole_stream(tmp_path, capsys):
    """Barrel distortion (drops events) with tangential terms; chunks of any size give the same events."""
    g = torch.Generator().manual_seed(0)
    n = 5000
    x, y = torch.randint(0, CAM.width, (n,), generator=g), torch.randint(0, CAM.height, (n,), generator=g)
    t = torch.sort(torch.randint(0, 10**6, (n,), generator=g)).values
    ev = EventStream(x, y, t, torch.randint(0, 2, (n,), generator=g))
    write_events_h5(tmp_path / "events.h5", ev, width=CAM.width, height=CAM.height)
    cam = dataclasses.replace(CAM, distortion=(-0.3, 0.1, 1e-3, -5e-4, 0.0))
    whole = undistort_events(read_events_h5(tmp_path / "events.h5"), cam)
    assert 0 < len(whole) < n
    for chunk in (1, 333, n):
        got = read_camera_events(tmp_path / "events.h5", cam, chunk=chunk)
        for f in "xytp":
            assert torch.equal(getattr(got, f), getattr(whole, f)), (chunk, f)
        assert f"dropped {n - len(whole)} " in capsys.readouterr().err


def test_track_reads_any_event_format_with_events(dirs, tmp_path, capsys):
    """The pinhole recording converted to text and npz and given with ``--events`` is tracked to the same poses; a
    directory without events.h5 and without ``--events`` is refused in one line."""
    from torchevtrack.io.formats import write_events

    seq = dirs / "pinhole"
    assert main(["track", str(seq), "--out", str(tmp_path / "h5.txt"), "--quiet", "--no-recover"]) == 0
    events = read_events_h5(seq / "events.h5")
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in ("camera.json", "mesh.ply", "gt_poses.txt"):
        shutil.copy(seq / f, bare / f)
    for name in ("ev.txt", "ev.npz"):
        write_events(tmp_path / name, events, width=CAM.width, height=CAM.height)
        out = tmp_path / f"{name}.poses.txt"
        assert main(["track", str(bare), "--events", str(tmp_path / name), "--out", str(out), "--quiet",
                     "--no-recover"]) == 0
        assert out.read_text() == (tmp_path / "h5.txt").read_text(), name
    capsys.readouterr()
    assert main(["track", str(bare), "--out", str(tmp_path / "none.txt")]) == 2
    assert "has no events.h5: give the event file with --events" in capsys.readouterr().err
    assert not (tmp_path / "none.txt").exists()


def test_bench_json_stays_one_json_object_on_a_distorted_camera(dirs, capsys):
    """``bench`` reads a distorted camera's events as ``track`` does; the undistortion's note must not break its
    ``--json`` output (one JSON object on stdout)."""
    import json

    assert main(["bench", str(dirs / "distorted"), "--duration", "0.01", "--batch", "1", "--warmup", "0",
                 "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["n_updates"] == 5
    assert "dropped 0" in err


def test_track_reports_the_tracking_rate_apart_from_the_searches(dirs, capsys):
    """A search blocks its update for about a second: the summary gives the rate of the tracking without it, and the
    search time beside it (a short recording's rate would otherwise be mostly the search's)."""
    out = dirs / "searched.txt"
    assert main(["track", str(dirs / "pinhole"), "--out", str(out), "--quiet", "--set",
                 "recover.start_after_us=20000"]) == 0  # the start search within the 40 ms recording
    printed = capsys.readouterr().out
    m = re.search(r"(\d+) poses from \d+ events, \d+ updates/s \(\d+\.\d s, and \d+\.\d s in 1 search\)", printed)
    assert m, printed
    assert int(m[1]) == 20
    assert re.search(r"lost in \d+ of 20 updates; 1 search, [01] restarts?\n", printed), printed


def test_start_tracks_as_the_recording_cut_there(dirs, tmp_path, capsys):
    """``--start S`` tracks as the recording whose events and ground truth begin at ``S``: from the first
    ground-truth pose at or after it, or from ``--init`` at ``S``; a time outside the events is refused in one line."""
    from torchevtrack.io.poses import read_tum, write_tum

    seq = dirs / "pinhole"
    events = read_events_h5(seq / "events.h5")
    t_gt, poses = read_tum(seq / "gt_poses.txt")
    t_s = int(events.t[len(events) // 2])  # an event's time: the cut recording's first event is there
    k = int(torch.searchsorted(t_gt, t_s))
    assert t_gt[k] > t_s and k > 0  # the ground truth's next pose is later: tracking from there
    cut = tmp_path / "cut"
    cut.mkdir()
    for f in ("camera.json", "mesh.ply"):
        shutil.copy(seq / f, cut / f)
    write_events_h5(cut / "events.h5", events.slice_time(t_s, events.t_end + 1), width=CAM.width, height=CAM.height)
    write_tum(cut / "gt_poses.txt", t_gt[k:], poses[k:])
    init = " ".join(f"{v:.9f}" for v in (*poses[k, :3].tolist(), *poses[k, 4:].tolist(), poses[k, 3].item()))
    for extra in ([], ["--init", init]):
        a, b = tmp_path / "a.txt", tmp_path / "b.txt"
        assert main(["track", str(seq), "--start", f"{t_s / 1e6:.6f}", "--out", str(a), "--quiet", "--no-recover",
                     *extra]) == 0
        assert main(["track", str(cut), "--out", str(b), "--quiet", "--no-recover", *extra]) == 0
        first = read_tum(a)[0][0]
        assert int(first) == (t_s if extra else int(t_gt[k])) + 2000, extra
        assert a.read_text() == b.read_text(), extra
    capsys.readouterr()
    assert main(["track", str(seq), "--start", "5", "--out", str(tmp_path / "late.txt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchevtrack track: error: --start 5.0 s is outside the events (") and "\n" not in err
    assert not (tmp_path / "late.txt").exists()
