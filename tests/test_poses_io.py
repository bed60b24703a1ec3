import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchevtrack.io import poses as io


def _trajectory(n=20, seed=0, dt_us=33_333):
    rot = Rotation.random(n, random_state=seed)
    q = rot.as_quat()[:, [3, 0, 1, 2]]
    q[q[:, 0] < 0] *= -1
    t = np.random.default_rng(seed).normal(size=(n, 3)) * 0.1 + [0, 0, 0.7]
    t_us = torch.arange(n, dtype=torch.int64) * dt_us - dt_us  # starts at a negative time
    return t_us, torch.from_numpy(np.concatenate((t, q), axis=1))


@pytest.mark.parametrize("suffix", [".txt", ".csv"])
def test_text_roundtrip(tmp_path, suffix):
    t, p = _trajectory()
    path = tmp_path / f"traj{suffix}"
    io.write_poses(path, t, p)
    t2, p2 = io.read_poses(path)
    assert t2.dtype == torch.int64 and p2.dtype == torch.float64
    assert torch.equal(t2, t)
    np.testing.assert_allclose(p2.numpy(), p.numpy(), atol=1e-9)


def test_bop_roundtrip(tmp_path):
    t, p = _trajectory(dt_us=40_000)  # 25 fps
    t = t + 40_000
    path = tmp_path / "scene_gt.json"
    io.write_poses(path, t, p, fps=25.0, obj_id=7)
    t2, p2 = io.read_poses(path, fps=25.0)
    assert torch.equal(t2, t)
    np.testing.assert_allclose(p2.numpy(), p.numpy(), atol=1e-12)
    t3, _ = io.read_bop_scene_gt(path, obj_id=7, times={str(i): 1000 * i for i in range(len(t))})
    assert torch.equal(t3, torch.arange(len(t)) * 1000)


def test_bop_roundtrip_30fps_grid(tmp_path):
    t = torch.tensor([round(k * 1e6 / 30) for k in range(10)])
    _, p = _trajectory(10)
    io.write_bop_scene_gt(tmp_path / "g.json", t, p, fps=30)
    t2, p2 = io.read_bop_scene_gt(tmp_path / "g.json", fps=30)
    assert torch.equal(t2, t)
    with pytest.raises(ValueError, match="frame grid"):
        io.write_bop_scene_gt(tmp_path / "h.json", t + 3, p, fps=30)


def test_csv_written_by_hand(tmp_path):
    # 90 deg about z: (qx, qy, qz, qw) = (0, 0, sin 45, cos 45); columns as in the EDOPT datasets
    s = math.sqrt(0.5)
    text = (
        "t,x,y,z,qx,qy,qz,qw\n"
        f"0.0,0.1,-0.2,0.5,0,0,{s},{s}\n"
        "0.002,0.1,-0.2,0.51,0,0,0,-1\n"
        f"1.5e-2,0,0,1,{s},0,0,{-s}\n"
    )
    (tmp_path / "gt.csv").write_text(text)
    t, p = io.read_poses(tmp_path / "gt.csv")
    assert t.tolist() == [0, 2000, 15000]
    np.testing.assert_allclose(p[0].numpy(), [0.1, -0.2, 0.5, s, 0, 0, s], atol=1e-15)
    np.testing.assert_allclose(p[1].numpy(), [0.1, -0.2, 0.51, 1, 0, 0, 0], atol=1e-15)  # sign made w >= 0
    np.testing.assert_allclose(p[2].numpy(), [0, 0, 1, s, -s, 0, 0], atol=1e-15)


def test_csv_header_in_other_order_and_headerless(tmp_path):
    (tmp_path / "a.csv").write_text("qw,qx,qy,qz,x,y,z,timestamp\n1,0,0,0,1,2,3,0.5\n")
    t, p = io.read_csv(tmp_path / "a.csv")
    assert t.tolist() == [500000] and p[0].tolist() == [1, 2, 3, 1, 0, 0, 0]
    (tmp_path / "b.csv").write_text("0.25,1,2,3,0,0,0,1\n")
    t, p = io.read_csv(tmp_path / "b.csv")
    assert t.tolist() == [250000] and p[0].tolist() == [1, 2, 3, 1, 0, 0, 0]


def test_bop_written_by_hand(tmp_path):
    # obj 2 at frames 0 and 3 (frame 1 lacks it), obj 5 is another object; R = 90 deg about x
    R90x = [1, 0, 0, 0, 0, -1, 0, 1, 0]
    data = {
        "0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [10, -20, 500], "obj_id": 2}],
        "1": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 400], "obj_id": 5}],
        "3": [
            {"cam_R_m2c": R90x, "cam_t_m2c": [0, 0, 600], "obj_id": 2},
            {"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 400], "obj_id": 5},
        ],
    }
    path = tmp_path / "scene_gt.json"
    path.write_text(json.dumps(data))
    t, p = io.read_poses(path, obj_id=2, fps=30.0)
    assert t.tolist() == [0, 100000]
    s = math.sqrt(0.5)
    np.testing.assert_allclose(p.numpy(), [[0.01, -0.02, 0.5, 1, 0, 0, 0], [0, 0, 0.6, s, s, 0, 0]], atol=1e-12)
    t, p = io.read_bop_scene_gt(path, obj_id=5, times=torch.tensor([5, 6, 9]))
    assert t.tolist() == [6, 9]
    with pytest.raises(ValueError, match=r"object ids \[2, 5\]"):
        io.read_bop_scene_gt(path, fps=30)
    with pytest.raises(ValueError, match="fps= or times="):
        io.read_bop_scene_gt(path, obj_id=2)
    with pytest.raises(ValueError, match="3 entries|frames"):
        io.read_bop_scene_gt(path, obj_id=2, times=torch.tensor([1, 2]))


def test_format_detection_and_override(tmp_path):
    t, p = _trajectory(5)
    io.write_poses(tmp_path / "x.pose", t, p, format="csv")
    assert io.detect_format(tmp_path / "x.pose") == "csv"
    assert torch.equal(io.read_poses(tmp_path / "x.pose")[0], t)
    io.write_tum(tmp_path / "y.dat", t, p)
    assert io.detect_format(tmp_path / "y.dat") == "tum"
    io.write_bop_scene_gt(tmp_path / "z.out", t + 33_333, p, fps=1e6 / 33_333)
    assert io.detect_format(tmp_path / "z.out") == "bop"
    # an explicit format beats the extension
    io.write_csv(tmp_path / "w.txt", t, p)
    assert torch.equal(io.read_poses(tmp_path / "w.txt", format="csv")[0], t)
    with pytest.raises(ValueError, match="format must be"):
        io.read_poses(tmp_path / "w.txt", format="xml")
    with pytest.raises(TypeError, match="only apply to BOP"):
        io.read_poses(tmp_path / "y.dat", fps=30)


def test_errors_name_file_and_line(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("t,x,y,z,qx,qy,qz,qw\n0,0,0,1,0,0,0,1\n0.1,0,0,1,0,0,zero,1\n")
    with pytest.raises(ValueError, match=r"bad\.csv:3: not a number"):
        io.read_poses(f)
    f.write_text("t,x,y,z,qx,qy,qz,qw\n0,0,0,1,0,0,0,1\n0.1,0,0,1,0,0,1\n")
    with pytest.raises(ValueError, match=r"bad\.csv:3: expected 8"):
        io.read_poses(f)
    f.write_text("t,x,y,z,qx,qy,qw\n0,0,0,1,0,0,1\n")
    with pytest.raises(ValueError, match=r"bad\.csv:1: .*lacks columns \['qz'\]"):
        io.read_poses(f)
    f.write_text("t,x,y,z,qx,qy,qz,qw\n0.1,0,0,1,0,0,0,1\n0.0,0,0,1,0,0,0,1\n")
    with pytest.raises(ValueError, match="not sorted"):
        io.read_poses(f)
    f.write_text("t,x,y,z,qx,qy,qz,qw\n0.1,0,0,1,0,0,0,2\n")
    with pytest.raises(ValueError, match="pose 1 is not unit norm"):
        io.read_poses(f)
    g = tmp_path / "bad.json"
    g.write_text('{"0": [{"obj_id": 1,\n "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1],\n "cam_t_m2c": [0, 0 500]}]}')
    with pytest.raises(ValueError, match=r"bad\.json:3: invalid JSON"):
        io.read_poses(g, fps=30)
    g.write_text('{"0": [{"obj_id": 1, "cam_R_m2c": [2, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 500]}]}')
    with pytest.raises(ValueError, match="frame 0: cam_R_m2c is not a rotation"):
        io.read_poses(g, fps=30)
    with pytest.raises(FileNotFoundError, match="missing.txt"):
        io.read_poses(tmp_path / "missing.txt")
