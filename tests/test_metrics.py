import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchevtrack import geometry as g
from torchevtrack.stages.propagate import propagate
from torchevtrack import metrics as m

RNG = np.random.default_rng(0)


def _poses_from_scipy(rot: Rotation, t: np.ndarray) -> torch.Tensor:
    q = rot.as_quat()[:, [3, 0, 1, 2]]
    return torch.cat((torch.from_numpy(t), g.quat_canonical(torch.from_numpy(q))), dim=-1)


def _random_pair(n, seed=1):
    rng = np.random.default_rng(seed)
    r_gt = Rotation.random(n, random_state=seed)
    r_pr = Rotation.random(n, random_state=seed + 100)
    t_gt = rng.normal(size=(n, 3)) * 0.1 + [0, 0, 0.6]
    t_pr = t_gt + rng.normal(size=(n, 3)) * 0.02
    return r_pr, t_pr, r_gt, t_gt, _poses_from_scipy(r_pr, t_pr), _poses_from_scipy(r_gt, t_gt)


def test_rotation_and_translation_errors_match_scipy():
    r_pr, t_pr, r_gt, t_gt, pred, gt = _random_pair(200)
    e = m.pose_errors(pred, gt)
    rel = r_pr * r_gt.inv()  # R R_gt^T
    np.testing.assert_allclose(e["re"].numpy(), rel.magnitude(), atol=1e-10)
    np.testing.assert_allclose(e["re_xyz"].numpy(), rel.as_rotvec(), atol=1e-9)
    np.testing.assert_allclose(e["te"].numpy(), np.linalg.norm(t_pr - t_gt, axis=1), atol=1e-14)
    np.testing.assert_allclose(e["te_xyz"].numpy(), t_pr - t_gt, atol=1e-14)
    # the textbook arccos form, on the matrices
    R, Rg = r_pr.as_matrix(), r_gt.as_matrix()
    tr = np.einsum("nij,nij->n", R, Rg)  # tr(R Rg^T)
    np.testing.assert_allclose(m.rotation_error(pred, gt).numpy(), np.arccos(np.clip((tr - 1) / 2, -1, 1)), atol=1e-7)
    np.testing.assert_allclose(m.translation_error(pred, gt).numpy(), e["te"].numpy())


def test_rotation_error_is_accurate_for_tiny_angles_and_sign_flips():
    gt = torch.tensor([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).repeat(2, 1)
    pred = gt.clone()
    pred[0, 3:] = g.quat_exp(torch.tensor([1e-9, 0.0, 0.0], dtype=torch.float64))
    pred[1, 3:] = -g.quat_exp(torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))  # same rotation, other sign
    re = m.rotation_error(pred, gt)
    assert abs(float(re[0]) - 1e-9) < 1e-18
    assert abs(float(re[1]) - 0.3) < 1e-12


def test_add_matches_bruteforce():
    _, _, _, _, pred, gt = _random_pair(7, seed=3)
    pts = torch.from_numpy(RNG.normal(size=(50, 3)) * 0.05)
    expected = []
    for p, q in zip(pred, gt):
        Rp, Rq = g.quat_to_matrix(p[3:]).numpy(), g.quat_to_matrix(q[3:]).numpy()
        a = pts.numpy() @ Rp.T + p[:3].numpy()
        b = pts.numpy() @ Rq.T + q[:3].numpy()
        expected.append(np.linalg.norm(a - b, axis=1).mean())
    np.testing.assert_allclose(m.add_error(pred, gt, pts, chunk=3).numpy(), expected, atol=1e-12)


def test_adds_matches_bruteforce_nearest_neighbours():
    _, _, _, _, pred, gt = _random_pair(9, seed=4)
    pts = torch.from_numpy(RNG.normal(size=(80, 3)) * 0.05)
    expected = []
    for p, q in zip(pred, gt):
        Rp, Rq = g.quat_to_matrix(p[3:]).numpy(), g.quat_to_matrix(q[3:]).numpy()
        a = pts.numpy() @ Rp.T + p[:3].numpy()
        b = pts.numpy() @ Rq.T + q[:3].numpy()
        d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)  # (M, M)
        expected.append(d.min(axis=1).mean())
    np.testing.assert_allclose(m.adds_error(pred, gt, pts, chunk=4).numpy(), expected, atol=1e-12)


def test_adds_is_zero_for_a_symmetry_while_add_is_not():
    cube = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float64) * 0.03
    gt = torch.tensor([[0.01, 0.02, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    pred = gt.clone()
    pred[0, 3:] = g.quat_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert float(m.adds_error(pred, gt, cube)) < 1e-12
    assert float(m.add_error(pred, gt, cube)) == pytest.approx(0.03 * 2 * math.sqrt(2) * math.sin(math.pi / 4), rel=1e-9)


def test_auc_hand_computed_and_against_discrete_curve():
    # accuracy(tau) integrated over [0, 0.1] / 0.1: e=0 -> 1, e=0.05 -> 0.5, e=0.2 -> 0
    assert m.auc(torch.tensor([0.0, 0.05, 0.2], dtype=torch.float64)) == pytest.approx(0.5, abs=1e-15)
    assert m.auc(torch.tensor([0.025], dtype=torch.float64)) == pytest.approx(0.75, abs=1e-15)
    assert m.auc(torch.zeros(10)) == 1.0
    e = torch.from_numpy(RNG.uniform(0, 0.15, size=300))
    thr = np.linspace(0, 0.1, 100001)
    acc = (e.numpy()[None, :] < thr[:, None]).mean(axis=1)
    assert m.auc(e) == pytest.approx(np.trapezoid(acc, thr) / 0.1, abs=1e-4)


def test_failure_rule_49_vs_50_consecutive():
    n = 200
    te, re = torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    te[10:59] = 0.08  # 49 bad samples in a row
    assert m.failure_index(te, re) is None
    te[100:150] = 0.071  # 50 in a row
    assert m.failure_index(te, re) == 100
    te2 = torch.zeros(n, dtype=torch.float64)
    re2 = torch.zeros(n, dtype=torch.float64)
    re2[30:80] = math.radians(40.5)
    assert m.failure_index(te2, re2) == 30
    re2[30:80] = math.radians(39.9)  # below the threshold: not bad
    te2[30:80] = 0.07  # equal to the threshold: not bad (strict >)
    assert m.failure_index(te2, re2) is None
    # mixed causes still make one run
    te3, re3 = torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    te3[5:30], re3[30:55] = 0.1, 1.0
    assert m.failure_index(te3, re3) == 5


def _reference_failure(te, re):
    run = 0
    for i, (a, b) in enumerate(zip(te.tolist(), re.tolist())):
        run = run + 1 if (a > 0.07 or b > math.radians(40)) else 0
        if run == 50:
            return i - 49
    return None


def test_failure_rule_matches_sequential_reference():
    rng = np.random.default_rng(5)
    for trial in range(30):
        bad = rng.random(400) < rng.uniform(0.9, 1.0)
        te = torch.from_numpy(np.where(bad, 0.1, 0.0))
        re = torch.zeros(400, dtype=torch.float64)
        assert m.failure_index(te, re) == _reference_failure(te, re)


def _traj(t_us, v=(0.1, -0.05, 0.02), w=(0.5, -1.0, 2.0)):
    """Constant twist motion, sampled exactly: translation linear, rotation exp(w t) q0."""
    s = torch.as_tensor(t_us, dtype=torch.float64)[:, None] * 1e-6
    t = torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64) + s * torch.tensor(v, dtype=torch.float64)
    q0 = g.quat_exp(torch.tensor([0.2, 0.1, -0.3], dtype=torch.float64))
    q = g.quat_mul(g.quat_exp(s * torch.tensor(w, dtype=torch.float64)), q0)
    return torch.cat((t, g.quat_canonical(q)), dim=-1)


def test_perfect_prediction_scores_zero():
    t = torch.arange(0, 200_000, 2000)
    gt = _traj(t)
    pts = torch.from_numpy(RNG.normal(size=(100, 3)) * 0.05)
    r = m.evaluate(t, gt.clone(), t, gt, mesh_points=pts)
    assert r["rmse_t_cm"] < 1e-12 and r["rmse_r_deg"] < 1e-6
    assert r["add_auc"] == pytest.approx(1.0, abs=1e-9) and r["adds_auc"] == pytest.approx(1.0, abs=1e-9)
    assert not r["failed"] and r["first_failure_s"] is None
    assert r["n_poses"] == 100 and r["n_dropped"] == 0


def test_constant_offsets():
    t = torch.arange(0, 100_000, 1000)
    gt = _traj(t)
    pred = gt.clone()
    pred[:, :3] += torch.tensor([0.006, 0.0, -0.008], dtype=torch.float64)  # 1 cm
    r = m.evaluate(t, pred, t, gt)
    assert r["rmse_t_cm"] == pytest.approx(1.0, abs=1e-12)
    assert r["std_t_cm"] == pytest.approx(0.0, abs=1e-12)
    assert r["mean_t_cm"] == pytest.approx(1.0, abs=1e-12) and r["median_t_cm"] == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r["rmse_t_xyz_cm"], [0.6, 0.0, 0.8], atol=1e-12)
    assert r["add_auc"] is None and r["adds_auc"] is None
    pred = gt.clone()
    axis = torch.tensor([1.0, 2.0, -2.0], dtype=torch.float64) / 3.0
    dq = g.quat_exp(axis * math.radians(10.0))
    pred[:, 3:] = g.quat_mul(dq, gt[:, 3:])  # R = dR R_gt: R R_gt^T = dR
    r = m.evaluate(t, pred, t, gt)
    assert r["rmse_r_deg"] == pytest.approx(10.0, abs=1e-9)
    assert r["std_r_deg"] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(r["rmse_r_xyz_deg"], (axis.abs() * 10).tolist(), atol=1e-9)
    assert r["rmse_t_cm"] < 1e-12


def test_std_is_population_std_and_rmse():
    _, _, _, _, pred, gt = _random_pair(40, seed=8)
    t = torch.arange(40, dtype=torch.int64) * 1000
    r = m.evaluate(t, pred, t, gt)
    te = np.linalg.norm((pred[:, :3] - gt[:, :3]).numpy(), axis=1) * 100
    assert r["rmse_t_cm"] == pytest.approx(np.sqrt(np.mean(te**2)), rel=1e-12)
    assert r["std_t_cm"] == pytest.approx(np.std(te, ddof=0), rel=1e-10)
    assert r["median_t_cm"] == pytest.approx(np.sort(te)[19], rel=1e-12)  # torch median: lower middle


def test_failure_in_evaluate_reports_time():
    t = torch.arange(0, 100) * 10_000 + 1_000_000
    gt = _traj(t)
    pred = gt.clone()
    pred[40:, 0] += 0.1  # 60 bad samples from index 40
    r = m.evaluate(t, pred, t, gt)
    assert r["failed"] and r["first_failure_index"] == 40
    assert r["first_failure_s"] == pytest.approx(1.4)


def test_time_alignment_with_gt_at_another_rate():
    gt_t = torch.arange(0, 300_001, 10_000)  # 100 Hz
    pred_t = torch.arange(-20_000, 340_000, 3_333)  # ~300 Hz, overhangs both ends
    inside = (pred_t >= 0) & (pred_t <= 300_000)
    # constant twist: translation linear and q(t) = exp(w t) q0 a geodesic, so linear + slerp
    # interpolation of the 100 Hz samples reproduces the ~300 Hz samples exactly
    gt, pred = _traj(gt_t), _traj(pred_t)
    r = m.evaluate(pred_t, pred, gt_t, gt)
    assert r["n_poses"] == int(inside.sum()) and r["n_dropped"] == int((~inside).sum()) > 0
    assert r["rmse_t_cm"] < 1e-10 and r["rmse_r_deg"] < 1e-8
    e = m.per_pose_errors(pred_t, pred, gt_t, gt)
    assert torch.equal(e["t_us"], pred_t[inside]) and torch.equal(e["keep"], inside)


def test_time_alignment_against_scipy_slerp():
    from scipy.spatial.transform import Slerp

    gt_t = torch.arange(0, 100_001, 25_000)
    r_gt = Rotation.random(len(gt_t), random_state=2)
    t_gt = RNG.normal(size=(len(gt_t), 3))
    gt = _poses_from_scipy(r_gt, t_gt)
    pred_t = torch.tensor([0, 7_000, 30_000, 62_500, 99_999, 100_000, 100_001])
    pred = _poses_from_scipy(Rotation.identity(len(pred_t)), np.zeros((len(pred_t), 3)))
    e = m.per_pose_errors(pred_t, pred, gt_t, gt)
    q = pred_t[:-1].numpy()
    r_ref = Slerp(gt_t.numpy(), r_gt)(q)
    t_ref = np.stack([np.interp(q, gt_t.numpy(), t_gt[:, k]) for k in range(3)], axis=1)
    np.testing.assert_allclose(e["re"].numpy(), r_ref.magnitude(), atol=1e-9)
    np.testing.assert_allclose(e["te"].numpy(), np.linalg.norm(t_ref, axis=1), atol=1e-12)


def test_twists_from_poses_and_velocity_errors():
    t = torch.arange(0, 50_000, 1000)
    v, w = (0.1, -0.05, 0.02), (0.5, -1.0, 2.0)
    # Constant twist in the package convention (dP/dt = v + w x P), moved exactly (propagate is
    # checked against solve_ivp in test_propagate.py).
    twist = torch.tensor([v + w], dtype=torch.float64).expand(len(t), 6)
    gt = propagate(_traj(t[:1]).expand(len(t), 7), twist, t.double() * 1e-6)
    tw = m.twists_from_poses(t, gt)
    np.testing.assert_allclose(tw.numpy(), np.tile(np.array(v + w), (len(t), 1)), atol=1e-9)
    pred_tw = tw.clone()
    pred_tw[:, 0] += 0.03
    pred_tw[:, 5] += math.radians(4.0)
    r = m.evaluate(t, gt, t, gt, pred_twists=pred_tw)
    assert r["rmse_v_cm_s"] == pytest.approx(3.0, abs=1e-6)
    assert r["rmse_w_deg_s"] == pytest.approx(4.0, abs=1e-6)
    ev, ew = m.velocity_errors(torch.tensor([[3.0, 4, 0, 0, 0, 1]]), torch.zeros(1, 6))
    assert float(ev) == 5.0 and float(ew) == 1.0


def test_symmetric_flag_selects_adds():
    cube = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float64) * 0.05
    t = torch.arange(10) * 1000
    gt = _traj(t, w=(0.0, 0.0, 0.0))
    pred = gt.clone()
    pred[:, 3:] = g.quat_mul(gt[:, 3:], g.quat_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)))
    r = m.evaluate(t, pred, t, gt, mesh_points=cube, symmetric=True)
    assert r["adds_auc"] == pytest.approx(1.0, abs=1e-9) and r["add_auc"] < 0.5
    assert r["add_s_auc"] == r["adds_auc"]
    assert m.evaluate(t, pred, t, gt, mesh_points=cube)["add_s_auc"] == r["add_auc"]


def test_bad_inputs():
    t = torch.arange(5) * 1000
    gt = _traj(t)
    with pytest.raises(TypeError, match="pred_t_us"):
        m.evaluate(t.double(), gt, t, gt)
    with pytest.raises(ValueError, match="pred_poses"):
        m.evaluate(t, gt[:, :6], t, gt)
    bad = gt.clone()
    bad[0, 3] = 2.0
    with pytest.raises(ValueError, match="unit norm"):
        m.evaluate(t, bad, t, gt)
    with pytest.raises(ValueError, match="sorted"):
        m.evaluate(t.flip(0), gt, t, gt)
    with pytest.raises(ValueError, match="no prediction"):
        m.evaluate(t + 10_000, gt, t, gt)
    with pytest.raises(ValueError, match="mesh_points"):
        m.evaluate(t, gt, t, gt, mesh_points=torch.zeros(4, 2))


# ---- the `torchevtrack eval` command -------------------------------------------------------------


def _sequence_dir(tmp_path):
    import trimesh

    from torchevtrack.io.poses import write_tum

    d = tmp_path / "seq"
    d.mkdir()
    t = torch.arange(0, 200_000, 2_000)
    gt = _traj(t)
    write_tum(d / "gt_poses.txt", t, gt)
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(d / "mesh.ply")
    return d, t, gt


def test_cli_eval_json_on_sequence_dir(tmp_path, capsys):
    import json

    from torchevtrack.cli import main
    from torchevtrack.io.poses import write_poses

    d, t, gt = _sequence_dir(tmp_path)
    pred = gt.clone()
    pred[:, 2] += 0.01  # 1 cm along the optical axis: ADD = 1 cm for every point -> AUC 0.9
    pred_t = t + 1_000  # the last prediction leaves the GT range and is dropped
    write_poses(tmp_path / "pred.csv", pred_t, _traj(pred_t) + (pred - gt))
    assert main(["eval", "--gt", str(d), "--pred", str(tmp_path / "pred.csv"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["n_poses"] == len(t) - 1 and r["n_dropped"] == 1
    assert r["rmse_t_cm"] == pytest.approx(1.0, abs=1e-6) and r["std_t_cm"] == pytest.approx(0.0, abs=1e-6)
    assert r["rmse_r_deg"] < 1e-5
    assert r["add_auc"] == pytest.approx(0.9, abs=1e-6)
    assert 0.9 - 1e-6 <= r["adds_auc"] <= 1.0
    assert r["n_mesh_points"] == 8 and r["failed"] is False


def test_cli_eval_summary_and_failure(tmp_path, capsys):
    from torchevtrack.cli import main
    from torchevtrack.io.poses import write_poses

    d, t, gt = _sequence_dir(tmp_path)
    pred = gt.clone()
    pred[30:, 0] += 0.2
    write_poses(tmp_path / "pred.txt", t, pred)
    assert main(["eval", "--gt", str(d / "gt_poses.txt"), "--pred", str(tmp_path / "pred.txt")]) == 0
    out = capsys.readouterr().out
    # a file --gt does not pick up the directory's mesh, but names it
    assert f"n/a (no mesh; --gt {d} also reads its mesh.ply: ADD / ADD-S, a plain can's spin left out)" in out
    assert "FAILED at 0.060000 s (pose 30" in out


def test_cli_eval_scores_the_lost_flags_beside_the_prediction(tmp_path, capsys):
    """track's side file: flags from pose 40 on detect a failure that began at pose 30 (2 ms apart) 20 ms late."""
    import json

    from torchevtrack.cli import main
    from torchevtrack.io.lost import write_lost
    from torchevtrack.io.poses import write_poses

    d, t, gt = _sequence_dir(tmp_path)
    pred = gt.clone()
    pred[30:, 0] += 0.2
    write_poses(tmp_path / "pred.txt", t, pred)
    argv = ["eval", "--gt", str(d / "gt_poses.txt"), "--pred", str(tmp_path / "pred.txt")]
    assert main(argv + ["--json"]) == 0
    assert "loss" not in json.loads(capsys.readouterr().out)  # no side file, no loss verdict
    lost = torch.zeros(len(t), dtype=torch.bool)
    lost[5:8] = True
    lost[40:] = True
    write_lost(tmp_path / "pred.lost.txt", t, lost)
    assert main(argv + ["--json"]) == 0
    x = json.loads(capsys.readouterr().out)["loss"]
    assert (x["first_failure_us"], x["first_loss_us"], x["delay_us"]) == (60_000, 10_000, 20_000)
    assert (x["declarations"], x["false_alarms"], x["recoveries"], x["missed"]) == (2, 1, 1, False)
    assert main(argv) == 0
    assert "lost flags   : the failure was detected 20 ms after the failure run began: 2 declaration(s), 1 false " \
        "alarm(s)" in capsys.readouterr().out
    write_lost(tmp_path / "pred.lost.txt", t[:-1], lost[:-1])
    assert main(argv) == 2
    assert "pred.lost.txt: its times are not those of" in capsys.readouterr().err


def test_cli_eval_leaves_a_plain_cylinders_spin_out_as_the_benchmark_does(tmp_path, capsys):
    """A prediction spun 60 deg about a plain (uncoloured) cylinder's axis fails the whole-rotation rule only; a box
    (no continuous symmetry) gets no symmetric lines."""
    import trimesh

    from torchevtrack.cli import main
    from torchevtrack.io.poses import write_tum

    t = torch.arange(0, 200_000, 2_000)
    gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(len(t), 7)
    pred = gt.clone()
    pred[:, 3:] = torch.tensor([math.cos(math.radians(30)), 0.0, 0.0, math.sin(math.radians(30))])  # 60 deg about z
    pred[:, 0] += 0.002
    write_tum(tmp_path / "gt.txt", t, gt)
    write_tum(tmp_path / "pred.txt", t, pred)
    trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48).export(tmp_path / "can.ply")
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(tmp_path / "box.ply")
    args = ["eval", "--gt", str(tmp_path / "gt.txt"), "--pred", str(tmp_path / "pred.txt"), "--mesh"]
    assert main(args + [str(tmp_path / "can.ply")]) == 0
    out = capsys.readouterr().out
    assert "rotation     : RMSE 60.000 deg" in out and "rotation sym : RMSE 0.000 deg" in out
    assert "failure      : FAILED at 0.000000 s" in out and "failure sym  : no" in out
    assert main(args + [str(tmp_path / "box.ply")]) == 0
    assert "sym" not in capsys.readouterr().out


def test_cli_eval_bop_gt_and_mesh_subsampling(tmp_path, capsys):
    import json

    import trimesh

    from torchevtrack.cli import main
    from torchevtrack.metrics import load_mesh_points
    from torchevtrack.io.poses import write_poses

    t = torch.tensor([round(k * 1e6 / 50) for k in range(40)])
    gt = _traj(t)
    write_poses(tmp_path / "scene_gt.json", t, gt, fps=50)
    write_poses(tmp_path / "pred.txt", t, gt)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    sphere.export(tmp_path / "sphere.ply")
    pts = load_mesh_points(tmp_path / "sphere.ply")
    assert pts.shape == (2000, 3) and len(sphere.vertices) > 2000
    assert torch.equal(pts, load_mesh_points(tmp_path / "sphere.ply"))
    np.testing.assert_allclose(pts.norm(dim=1).numpy(), 0.05, rtol=1e-6)  # real vertices
    assert len(np.unique(pts.numpy(), axis=0)) == 2000
    argv = ["eval", "--gt", str(tmp_path / "scene_gt.json"), "--pred", str(tmp_path / "pred.txt"), "--fps", "50"]
    assert main(argv + ["--mesh", str(tmp_path / "sphere.ply"), "--symmetric", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["n_poses"] == 40 and r["rmse_t_cm"] < 1e-6 and r["adds_auc"] == pytest.approx(1.0, abs=1e-6)
    assert r["n_mesh_points"] == 2000
    assert main(argv[:-2]) == 2  # BOP without a frame rate: a clear error, no traceback
    assert "fps" in capsys.readouterr().err


def test_cli_eval_missing_file(tmp_path, capsys):
    from torchevtrack.cli import main

    assert main(["eval", "--gt", str(tmp_path / "nope.txt"), "--pred", str(tmp_path / "nope.txt")]) == 2
    assert "nope.txt" in capsys.readouterr().err


# -- continuous symmetry -------------------------------------------------------------------------------
def test_rotation_error_modulo_an_axis_against_scipy():
    """Spins about the axis (object frame) cost nothing; a tilt of phi perpendicular to it costs phi;
    in general the error is the angle between the rotated axes (scipy oracle)."""
    rng = np.random.default_rng(5)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    perp = np.cross(axis, [1.0, 0.0, 0.0])
    perp /= np.linalg.norm(perp)
    r_gt = Rotation.random(50, random_state=3)
    t = np.zeros((50, 3)) + [0, 0, 0.5]
    gt = _poses_from_scipy(r_gt, t)
    spin = _poses_from_scipy(r_gt * Rotation.from_rotvec(np.outer(rng.uniform(-3, 3, 50), axis)), t)
    phi = rng.uniform(0, 2.5, 50)
    tilt = _poses_from_scipy(r_gt * Rotation.from_rotvec(phi[:, None] * perp), t)
    a = torch.from_numpy(axis)
    assert m.rotation_error(spin, gt, a).abs().max() < 1e-7 and m.rotation_error(spin, gt).min() > 1e-3
    np.testing.assert_allclose(m.rotation_error(tilt, gt, a).numpy(), phi, atol=1e-9)
    r_pr, _, r_gt2, _, pred, gt2 = _random_pair(100, seed=7)
    want = np.arccos(np.clip((r_pr.apply(axis) * r_gt2.apply(axis)).sum(1), -1, 1))
    np.testing.assert_allclose(m.rotation_error(pred, gt2, a).numpy(), want, atol=1e-7)
    with pytest.raises(ValueError, match="axis"):
        m.rotation_error(pred, gt2, torch.zeros(3))


def test_evaluate_reports_the_error_modulo_symmetry_and_its_failures():
    """A tracker that spins the object about its symmetry axis by 60 deg fails the plain rule only."""
    t_us = torch.arange(200) * 2000
    gt = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64).expand(200, 7)
    pred = gt.clone()
    pred[:, 3:] = torch.tensor([math.cos(math.radians(30)), 0.0, 0.0, math.sin(math.radians(30))])  # 60 deg about z
    out = m.evaluate(t_us, pred, t_us, gt, symmetry_axis=torch.tensor([0.0, 0.0, 1.0]))
    assert out["failed"] and not out["failed_sym"] and out["first_failure_sym_s"] is None
    assert out["rmse_r_deg"] == pytest.approx(60.0) and out["rmse_r_sym_deg"] < 1e-6
    assert "rmse_r_sym_deg" not in m.evaluate(t_us, pred, t_us, gt)


def test_symmetry_axis_of_meshes():
    import trimesh

    from torchevtrack.mesh import hidden_symmetry_axis, load_mesh, symmetry_axis

    assert np.allclose(symmetry_axis(load_mesh("can")), [0, 0, 1], atol=1e-6)
    assert hidden_symmetry_axis(load_mesh("can")) is None  # its vertex colours show turns about the axis
    assert symmetry_axis(load_mesh("box")) is None
    rot = Rotation.from_rotvec([0.3, -0.5, 0.2])
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48)
    cyl.apply_transform(np.block([[rot.as_matrix(), np.array([[0.01], [0.02], [0.0]])], [np.zeros((1, 3)), 1.0]]))
    got = symmetry_axis(cyl)
    assert abs(abs(got @ rot.apply([0.0, 0.0, 1.0])) - 1) < 1e-6
    assert np.array_equal(hidden_symmetry_axis(cyl), got)  # no colours: nothing shows the turns
    squashed = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48)
    squashed.apply_scale([1.0, 1.3, 1.0])  # an elliptic cylinder has no continuous symmetry
    assert symmetry_axis(squashed) is None


def test_batched_evaluate_equals_one_call_per_element():
    t = torch.arange(0, 300_000, 2000)
    gt = torch.stack([_traj(t), _traj(t, v=(0.0, 0.1, 0.0))])  # (2, N, 7): own ground truth per element
    pred = gt.clone()
    pred[0, :, 0] += 0.01
    pred[1, :, 3:] = g.quat_mul(g.quat_exp(torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)), gt[1, :, 3:])
    pts = torch.from_numpy(RNG.normal(size=(2, 50, 3)) * 0.05)
    got = m.evaluate(t.expand(2, -1), pred, t.expand(2, -1), gt, mesh_points=pts)
    assert isinstance(got, list) and len(got) == 2
    for i in range(2):
        assert got[i] == m.evaluate(t, pred[i], t, gt[i], mesh_points=pts[i])
    shared = m.evaluate(t.expand(2, -1), pred, t, gt[0], mesh_points=pts[0])  # ground truth and points shared
    assert shared[0] == m.evaluate(t, pred[0], t, gt[0], mesh_points=pts[0])
    assert shared[1]["rmse_t_cm"] > 1.0
    with pytest.raises(ValueError, match="pred_t_us"):
        m.evaluate(t, pred, t, gt)
    with pytest.raises(ValueError, match="mesh_points"):
        m.evaluate(t.expand(2, -1), pred, t, gt[0], mesh_points=pts[:, None])
