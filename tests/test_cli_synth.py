import json
import warnings

import h5py
import numpy as np
import pytest
import torch
import trimesh
from scipy.ndimage import binary_dilation

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.geometry import interpolate_poses, transform_points
from torchevtrack.render import Renderer
from torchevtrack.synth.generate import frame_times, generate_sequence
from torchevtrack.synth.sequence import Sequence
from torchevtrack.synth.trajectory import bbox_corners, make_trajectory

CAM = Camera(64, 48, 50.0, 50.0, 32.0, 24.0)
TINY = ["--width", "64", "--height", "48", "--fx", "50", "--fy", "50", "--quiet"]


def synth(out, seed, obj="can", motion="regular"):
    rc = main(["synth", "--object", obj, "--motion", motion, "--duration", "0.05", "--seed", str(seed),
               "--out", str(out), *TINY])
    assert rc == 0


def datasets(path):
    with h5py.File(path) as f:
        return {k: f[k][()].tobytes() for k in ("x", "y", "t", "p")}


def test_same_seed_same_bytes(tmp_path):
    synth(tmp_path / "a", 7)
    synth(tmp_path / "b", 7)
    synth(tmp_path / "c", 8)
    a, b, c = (datasets(tmp_path / n / "events.h5") for n in "abc")
    assert len(a["t"]) > 0 and a == b and a != c
    assert (tmp_path / "a" / "events.h5").read_bytes() == (tmp_path / "b" / "events.h5").read_bytes()
    assert (tmp_path / "a" / "gt_poses.txt").read_bytes() == (tmp_path / "b" / "gt_poses.txt").read_bytes()


def test_sequence_contents_and_info(tmp_path, capsys):
    synth(tmp_path / "s", 1, motion="fast")
    seq = Sequence.load(tmp_path / "s")
    assert seq.camera == CAM
    assert seq.gt_t_us.tolist() == list(range(0, 50_001, 2000))  # 500 Hz
    assert len(seq.events) > 1000 and 0 < seq.events.p.double().mean() < 1
    assert seq.meta["object"] == "can" and seq.meta["motion"] == "fast" and seq.meta["seed"] == 1
    assert seq.meta["n_events"] == len(seq.events)
    med = seq.meta["speeds"]["image_speed_px_s"]["median"]
    assert 600 * 0.97 <= med <= 1500 * 1.03
    capsys.readouterr()
    assert main(["info", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert f"events     {len(seq.events)} over" in out and "500 Hz" in out
    assert main(["info", str(tmp_path / "s"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["events"] == len(seq.events) and info["gt_poses"] == 26 and info["textured_mesh"] is None
    (tmp_path / "s" / "gt_poses.txt").unlink()  # a recording: events and camera only
    assert main(["info", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert f"events     {len(seq.events)} over" in out and "gt poses   none" in out
    assert main(["info", str(tmp_path / "s"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["events"] == len(seq.events) and info["gt_poses"] == 0 and "pose_range" not in info
    (tmp_path / "s" / "camera.json").unlink()
    assert main(["info", str(tmp_path / "s")]) == 2
    assert "lacks camera.json" in capsys.readouterr().err


def test_frames_move_at_most_half_a_pixel():
    mesh = trimesh.creation.box((0.05, 0.06, 0.07))
    t_us, poses = make_trajectory("fast", 0.05, 0, Camera.default(), mesh)
    idx = frame_times(t_us, poses, Camera.default(), bbox_corners(mesh), 0.5)
    assert idx[0] == 0 and idx[-1] == len(t_us) - 1 and (torch.diff(idx) > 0).all()
    V = torch.from_numpy(np.asarray(mesh.vertices))
    uv = Camera.default().project(transform_points(poses[idx], V))
    step = torch.linalg.norm(torch.diff(uv, dim=0), dim=-1).amax(-1)
    assert float(step.max()) <= 0.5 + 1e-9 and float(step.median()) > 0.3  # not oversampled either


def test_a_depth_range_the_object_cannot_fit_is_raised_with_a_warning():
    mesh = trimesh.creation.box((0.05, 0.06, 0.07))  # bounding radius 0.052 m: fits CAM from ~0.21 m
    with pytest.warns(UserWarning, match="depth range 0.1-0.2 m raised"):
        _, poses = make_trajectory("regular", 0.05, 0, CAM, mesh, depth_range=(0.1, 0.2))
    assert float(poses[:, 2].min()) > 0.2  # above the whole requested range
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a range the object fits: no warning, depths inside it
        _, poses = make_trajectory("regular", 0.05, 0, CAM, mesh, depth_range=(0.4, 0.6))
    assert 0.4 <= float(poses[:, 2].min()) and float(poses[:, 2].max()) <= 0.6


def test_synth_says_in_one_line_when_the_depth_range_was_raised(tmp_path, capsys):
    rc = main(["synth", "--object", "box", "--duration", "0.02", "--depth", "0.05,0.1", "--out", str(tmp_path / "s"),
               *TINY])
    err = capsys.readouterr().err
    assert rc == 0 and "torchevtrack synth: warning: the object" in err and "raised to" in err
    assert "UserWarning" not in err and len(err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def grey_box_sequence(tmp_path_factory):
    # a plain grey box (no texture) brighter than the background everywhere
    path = tmp_path_factory.mktemp("mesh") / "box.ply"
    trimesh.creation.box((0.04, 0.05, 0.06)).export(path)
    return generate_sequence(str(path), "fast", 0.04, 5, CAM, progress=False)


def test_synth_leave_view_has_no_events_while_the_object_is_away(tmp_path, capsys):
    """``--leave-view START,AWAY``: the excursion is in meta.json, no event fires while the object is out of view (no
    noise asked for), events fire before and after; an excursion that would not end in time is a one-line error."""
    out = tmp_path / "away"
    assert main(["synth", "--object", "box", "--duration", "1.0", "--leave-view", "0.1,0.2", "--seed", "2", "--out",
                 str(out), *TINY]) == 0
    seq = Sequence.load(out)
    assert seq.meta["leave_view"] == {"start_s": 0.1, "away_s": 0.2}
    t = seq.events.t
    assert int(((t >= 450_000) & (t < 650_000)).sum()) == 0  # 0.1 + 0.35 s out, 0.2 s away
    assert int((t < 100_000).sum()) > 0 and int((t > 1_000_000 - 50_000).sum()) > 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    assert "depth range 0.3-0.7 m; leaves the view at 0.1 s for 0.2 s" in capsys.readouterr().out
    rc = main(["synth", "--object", "box", "--duration", "0.5", "--leave-view", "0.1,0.2", "--out",
               str(tmp_path / "late"), *TINY])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "would not be back in view" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "late").exists()


def test_events_only_where_the_object_was(grey_box_sequence):
    seq = grey_box_sequence
    entered_p, left_p = [], []
    with Renderer(seq.mesh, CAM) as r:
        for t0 in range(0, 40_000, 2000):
            t1 = t0 + 2000
            ev = seq.events.slice_time(t0, t1 + 1)
            assert len(ev) > 0
            d = r.render(interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t0, t1])), shaded=False).depth
            m0, m1 = (d[0] > 0).numpy(), (d[1] > 0).numpy()
            x, y = ev.x.long().numpy(), ev.y.long().numpy()
            swept = binary_dilation(m0 | m1, iterations=2)  # object at both ends, swept in between
            assert swept[y, x].all()
            # the bright object newly covering dark background: ON events; uncovering: OFF events
            entered_p.append(ev.p.numpy()[(m1 & ~binary_dilation(m0, iterations=2))[y, x]])
            left_p.append(ev.p.numpy()[(m0 & ~binary_dilation(m1, iterations=2))[y, x]])
    entered_p, left_p = np.concatenate(entered_p), np.concatenate(left_p)
    assert entered_p.size > 50 and left_p.size > 50
    assert entered_p.mean() > 0.9 and left_p.mean() < 0.1


def test_benchmark_names_and_seeds(tmp_path):
    assert main(["synth-benchmark", "--out", str(tmp_path), "--duration", "0.01", "--only", "potted_regular",
                 "--quiet"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["potted_regular", "suite.json"]
    meta = json.loads((tmp_path / "potted_regular" / "meta.json").read_text())
    assert meta["object"] == "010_potted_meat_can" and meta["motion"] == "regular"
    assert json.loads((tmp_path / "potted_regular" / "camera.json").read_text())["width"] == 640
    assert main(["synth-benchmark", "--out", str(tmp_path), "--only", "banana_fast"]) == 2


def test_info_on_a_missing_path_names_both_kinds(tmp_path, capsys):
    """`info` takes a sequence directory or an event file: a missing one is neither, and the error says so."""
    assert main(["info", str(tmp_path / "rec.h5")]) == 2
    assert capsys.readouterr().err.strip() == f"torchevtrack info: error: no such sequence directory or event file: " \
        f"{tmp_path / 'rec.h5'}"
