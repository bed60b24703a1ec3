"""Bad input on the command line: one line on stderr, exit status 2, no traceback, nothing written; a tracking
run that never moves exits 3 with a warning; `eval` with another time base."""

import json
import math
import re

import numpy as np
import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.events import EventStream
from torchevtrack.io.events_h5 import write_events_h5
from torchevtrack.io.poses import write_tum

CAM = Camera(160, 120, 150.0, 150.0, 79.5, 59.5)
INIT = "0 0 0.6 0 0 0 1"  # the box 0.6 m in front, identity rotation (qw last)


def _seq(tmp_path, events: EventStream | None = None):
    d = tmp_path / "seq"
    d.mkdir()
    CAM.save(d / "camera.json")
    if events is None:
        rng = np.random.default_rng(0)
        n = 2000
        events = EventStream.from_arrays(rng.integers(60, 100, n), rng.integers(40, 80, n),
                                         np.sort(rng.integers(0, 20_000, n)), rng.integers(0, 2, n))
    write_events_h5(d / "events.h5", events, width=CAM.width, height=CAM.height)
    return d


def _run(capsys, *argv) -> tuple[int, str]:
    code = main(list(argv))
    err = capsys.readouterr().err
    return code, err


def _one_line_error(err: str, text: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert text in lines[0], lines[0]


def test_out_pointing_at_a_directory_fails_before_the_run(tmp_path, capsys):
    d = _seq(tmp_path)
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path), "--mesh", "box", "--init", INIT, "--quiet")
    assert code == 2
    _one_line_error(err, "is a directory")


@pytest.mark.parametrize("key, value, text", [
    ("fx", "150", "camera fx must be a number"),
    ("cx", float("nan"), "camera cx must be finite"),
    ("fy", float("inf"), "camera fy must be finite and positive"),
    ("width", 100000, "camera width must be a positive whole number"),
])
def test_bad_camera_json(tmp_path, capsys, key, value, text):
    d = _seq(tmp_path)
    cam = json.loads((d / "camera.json").read_text())
    cam[key] = value
    (d / "camera.json").write_text(json.dumps(cam))
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", INIT)
    assert code == 2
    _one_line_error(err, text)
    assert not (tmp_path / "p.txt").exists()


@pytest.mark.parametrize("dtype, text", [(np.float64, "expected integers microseconds"),
                                         (np.float32, "expected integers microseconds")])
def test_float_second_timestamps(tmp_path, capsys, dtype, text):
    import h5py

    d = _seq(tmp_path)
    with h5py.File(d / "events.h5", "r+") as f:
        t = f["t"][:] / 1e6
        del f["t"]
        f["t"] = t.astype(dtype)
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", INIT)
    assert code == 2
    _one_line_error(err, text)


def test_wrapped_pixels_and_polarity_are_errors(tmp_path, capsys):
    import h5py

    d = _seq(tmp_path)
    with h5py.File(d / "events.h5", "r+") as f:
        x = f["x"][:].astype(np.int32)
        x[3] = 32768 + 70  # would wrap to -32698 in int16
        del f["x"]
        f["x"] = x
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", INIT)
    assert code == 2
    _one_line_error(err, "event 3 has x=32838, outside [0, 160)")


@pytest.mark.parametrize("init, text", [
    ("0 0 0.6 1 0 0 0.5", "has norm 1.118, not 1"),
    ("0 0 -0.6 0 0 0 1", "out of view at the start pose"),
    ("5 0 0.6 0 0 0 1", "out of view at the start pose"),
    ("0 0 0.6 0 0 1", "must be 7 finite numbers"),
])
def test_bad_start_pose(tmp_path, capsys, init, text):
    d = _seq(tmp_path)
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", init)
    assert code == 2
    _one_line_error(err, text)


def test_a_rounded_start_quaternion_is_renormalised():
    from torchevtrack.cli.track import parse_init

    # two typed decimals of a 30 deg turn about z: norm 0.9997; and 1.02, too far to be rounding
    pose = parse_init("0.1 0 0.6 0 0 0.26 0.966")
    n = math.hypot(0.26, 0.966)
    assert torch.allclose(pose, torch.tensor([0.1, 0, 0.6, 0.966 / n, 0, 0, 0.26 / n], dtype=torch.float64))
    with pytest.raises(ValueError, match="has norm 1.02, not 1"):
        parse_init("0 0 0.6 0 0 0 1.02")


def test_a_start_pose_filling_the_image_warns(tmp_path, capsys):
    from torchevtrack.cli.track import check_start_pose

    close = torch.tensor([0.0, 0.0, 0.13, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    assert "fills the whole image" in check_start_pose(CAM, "box", close)
    assert check_start_pose(CAM, "box", torch.tensor([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0])) is None  # 123 px wide


def test_a_small_object_warns_with_its_span():
    from torchevtrack.cli.track import SMALL_PX, check_start_pose

    # the built-in box (0.16 x 0.06 x 0.21 m) face on, its centre at 0.6 m: the near face (0.105 m closer) spans
    # 0.16 m x 150 px / 0.495 m = 48.5 px
    warning = check_start_pose(CAM, "box", torch.tensor([0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    span = int(re.search(r"spans (\d+) px", warning).group(1))
    assert abs(span - 0.16 * 150.0 / 0.495) <= 1.0 and f"below {SMALL_PX} px" in warning


def test_no_events_in_the_tracked_span(tmp_path, capsys):
    d = _seq(tmp_path, EventStream.from_arrays([5, 6], [5, 6], [500_000, 600_000], [1, 0]))
    write_tum(d / "gt_poses.txt", torch.tensor([0]), torch.tensor([[0.0, 0.0, 0.6, 1.0, 0.0, 0.0, 0.0]]))
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--duration", "0.1")
    assert code == 2
    _one_line_error(err, "no events between t = 0 and 100000 us")
    d2 = _seq(tmp_path / "empty", EventStream.empty()) if (tmp_path / "empty").mkdir() is None else None
    code, err = _run(capsys, "track", str(d2), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", INIT)
    assert code == 2
    _one_line_error(err, "nothing to track")


def test_a_run_that_never_moves_warns_and_exits_3(tmp_path, capsys):
    """Events only in a corner, far from the object: the poses are written, but the run is flagged."""
    rng = np.random.default_rng(0)
    n = 2000
    corner = EventStream.from_arrays(rng.integers(0, 8, n), rng.integers(0, 8, n), np.sort(rng.integers(0, 20_000, n)),
                                     rng.integers(0, 2, n))
    d = _seq(tmp_path, corner)
    code, err = _run(capsys, "track", str(d), "--out", str(tmp_path / "p.txt"), "--mesh", "box", "--init", INIT,
                     "--quiet")
    assert code == 3
    assert "warning: the pose never moved from the start pose" in err
    assert len((tmp_path / "p.txt").read_text().splitlines()) == 1 + 9


def _gt_and_pred(tmp_path, scale: float, offset_us: int):
    """A ground truth at 0..300 ms and a prediction of the same poses whose times are ``t * scale + offset``."""
    t = torch.arange(0, 300_001, 2000, dtype=torch.int64)
    poses = torch.zeros(len(t), 7, dtype=torch.float64)
    poses[:, 0] = t / 1e7
    poses[:, 2] = 0.6
    poses[:, 3] = 1.0
    write_tum(tmp_path / "gt.txt", t, poses)
    lines = ["# t tx ty tz qx qy qz qw"]
    for ti, p in zip(t.tolist(), poses.tolist()):
        lines.append(f"{ti * scale + offset_us:.0f} {p[0]} {p[1]} {p[2]} {p[4]} {p[5]} {p[6]} {p[3]}")
    (tmp_path / "pred.txt").write_text("\n".join(lines) + "\n")
    return tmp_path / "gt.txt", tmp_path / "pred.txt"


def test_eval_in_another_time_base_fails_and_the_flags_fix_it(tmp_path, capsys):
    gt, pred = _gt_and_pred(tmp_path, 1.0, 5_000_000)  # microseconds, and 5 s later
    code, err = _run(capsys, "eval", "--gt", str(gt), "--pred", str(pred))
    assert code == 2
    _one_line_error(err, "151 of 151 predicted poses")
    assert "--time-unit" in err
    code = main(["eval", "--gt", str(gt), "--pred", str(pred), "--time-unit", "us", "--t-offset", "-5", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["n_poses"] == 151 and out["n_dropped"] == 0
    assert out["rmse_t_cm"] < 1e-6  # the same poses, up to the digits of the files


def test_eval_names_a_missing_pose_file(tmp_path, capsys):
    gt, pred = _gt_and_pred(tmp_path, 1.0, 0)
    for argv, missing in ((["--gt", str(tmp_path / "no_gt"), "--pred", str(pred)], "no_gt"),
                          (["--gt", str(gt), "--pred", str(tmp_path / "no_pred")], "no_pred")):
        code, err = _run(capsys, "eval", *argv)
        assert code == 2
        _one_line_error(err, f"pose file not found: {tmp_path / missing}")


def test_warmup_with_no_workers_is_a_one_line_error(capsys):
    code, err = _run(capsys, "warmup", "--jobs", "0")
    assert code == 2
    _one_line_error(err, "--jobs must be >= 1, got 0")


def test_an_unknown_option_is_reported_by_its_command(tmp_path, capsys):
    """The command's own usage and name, not the top level's (which only says `COMMAND ...`); nothing written."""
    with pytest.raises(SystemExit) as e:
        main(["synth", "--object", "box", "--hand", "--out", str(tmp_path / "seq")])
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.startswith("usage: torchevtrack synth ") and "--occluder" in err, err
    assert err.strip().splitlines()[-1] == "torchevtrack synth: error: unrecognized arguments: --hand"
    assert not (tmp_path / "seq").exists()
