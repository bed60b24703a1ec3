"""Benchmark runner tests on two tiny synthetic sequences (160x120 sensor, 0.06 s each)."""

import copy
import json
import math
import re
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from torchevtrack.benchmark import METHOD_NAMES, run_benchmark, table_markdown
from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.config import ABLATIONS, TrackerConfig
from torchevtrack.io.poses import read_tum
from torchevtrack.metrics import evaluate, mesh_points, sym_failed
from torchevtrack.synth.generate import generate_sequence
from torchevtrack.synth.sequence import Sequence
from torchevtrack.tracker import EventPoseTracker
from torchevtrack.viz import GT_COLOUR, PRED_COLOUR, overlay_frames

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)
DURATION_S = 0.06
METHODS = ("full", "correction_only")
SEQS = {"cracker_regular": ("box", "regular", 1), "tomato_fast": ("can", "fast", 2)}
N_UPDATES = int(DURATION_S * 500)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    for name, (obj, motion, seed) in SEQS.items():
        generate_sequence(obj, motion, DURATION_S, seed=seed, camera=CAM, progress=False).save(root / name)
    (root / "not_a_sequence").mkdir()  # ignored: lacks the sequence files
    return root


@pytest.fixture(scope="module")
def run(bench, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    res = run_benchmark(bench, out, methods=METHODS, progress=False)
    return res, out


def _independent_points(mesh):
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) > 2000:  # the documented rule: 2000 vertices at evenly spaced indices
        v = v[np.round(np.linspace(0, len(v) - 1, 2000)).astype(int)]
    return torch.from_numpy(v)


def test_results_json_has_every_method_and_sequence(run):
    res, out = run
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(res))
    assert set(on_disk["results"]) == set(METHODS) and on_disk["methods"] == list(METHODS)
    assert on_disk["config"] == TrackerConfig().to_dict()
    assert {"cpu_count", "torch_version", "torch_threads"} <= set(on_disk["machine"])
    assert on_disk["torchevtrack_version"] and on_disk["date"]
    assert set(on_disk["sequences"]) == set(SEQS)
    assert on_disk["sequences"]["tomato_fast"]["group"] == "fast"
    assert on_disk["sequences"]["cracker_regular"]["mesh_points"] == 2000  # the box has > 2000 vertices
    for m in METHODS:
        assert len(on_disk["runs"][m]) == 1 and on_disk["runs"][m][0]["batch_size"] == 2  # one batch per method
        assert set(on_disk["results"][m]) == set(SEQS)
        for r in on_disk["results"][m].values():
            x = r["metrics"]
            for key in ("rmse_t_cm", "std_t_cm", "rmse_r_deg", "std_r_deg", "add_auc", "adds_auc", "failed"):
                assert key in x
            assert 0.0 <= x["add_auc"] <= 1.0 and 0.0 <= x["adds_auc"] <= 1.0
            assert x["n_poses"] == N_UPDATES and x["n_dropped"] == 0
            t = r["timing"]
            assert t["updates"] == N_UPDATES and t["wall_s"] > 0 and t["updates_per_s"] > 0
            assert (out / r["pose_file"]).is_file()


def test_scores_are_those_of_the_written_pose_files(run, bench):
    res, out = run
    for m in METHODS:
        for name in SEQS:
            seq = Sequence.load(bench / name)
            t_us, poses = read_tum(out / "poses" / m / f"{name}.txt")
            # One pose per 2 ms update from the first ground-truth time to the end.
            assert torch.equal(t_us, seq.gt_t_us[0] + 2000 * torch.arange(1, N_UPDATES + 1))
            expected = evaluate(t_us, poses, seq.gt_t_us, seq.gt_poses, mesh_points=_independent_points(seq.mesh))
            got = res["results"][m][name]["metrics"]
            assert got.keys() == expected.keys()
            for k, v in expected.items():
                if isinstance(v, float) or isinstance(v, list):
                    np.testing.assert_allclose(got[k], v, rtol=1e-12, atol=1e-12, err_msg=f"{m} {name} {k}")
                else:
                    assert got[k] == v, (m, name, k)


def _table(md: str, title: str) -> list[list[str]]:
    """The first Markdown table after the heading line starting with ``title``, as rows of cells."""
    rows = []
    for line in md.split(title, 1)[1].splitlines()[1:]:
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif rows:
            break
    return rows


CELL = re.compile(r"^([\d.]+)\(([\d.]+)\) / ([\d.]+)\(([\d.]+)\)(†?)$")


def test_table_numbers_are_those_of_results_json(run):
    res, out = run
    md = (out / "table.md").read_text()
    assert md == table_markdown(json.loads((out / "results.json").read_text()))
    rows = _table(md, "## Pose error")
    assert rows[0] == ["Method", "cracker_regular", "tomato_fast", "Mean"]  # regular before fast
    assert [r[0] for r in rows[2:]] == [METHOD_NAMES["correction_only"], METHOD_NAMES["full"]]  # paper row order
    for row, m in zip(rows[2:], ("correction_only", "full")):
        vals = []
        for cell, name in zip(row[1:3], ("cracker_regular", "tomato_fast")):
            x = res["results"][m][name]["metrics"]
            match = CELL.match(cell)
            assert match, cell
            want = (x["rmse_t_cm"], x["std_t_cm"], x["rmse_r_deg"], x["std_r_deg"])
            np.testing.assert_allclose([float(g) for g in match.groups()[:4]], want, atol=0.005 + 1e-9)
            assert (match.group(5) == "†") == x["failed"]
            vals.append(want)
        mean = CELL.match(row[3])
        np.testing.assert_allclose([float(g) for g in mean.groups()[:4]], np.mean(vals, axis=0), atol=0.005 + 1e-9)
    auc = _table(md, "## ADD-S AUC")
    assert auc[0] == rows[0]
    for row, m in zip(auc[2:], ("correction_only", "full")):
        want = [100 * res["results"][m][n]["metrics"]["adds_auc"] for n in ("cracker_regular", "tomato_fast")]
        np.testing.assert_allclose([float(c) for c in row[1:]], want + [np.mean(want)], atol=0.005 + 1e-9)


def test_table_marks_failures_with_a_footnote(run):
    res = copy.deepcopy(run[0])
    assert "†" not in table_markdown(res)
    res["results"]["full"]["tomato_fast"]["metrics"]["failed"] = True
    md = table_markdown(res)
    rows = _table(md, "## Pose error")
    full = next(r for r in rows if r[0] == METHOD_NAMES["full"])
    assert full[2].endswith("†") and not full[1].endswith("†") and not full[3].endswith("†")
    assert "† failed: translation error > 7 cm or rotation error > 40 deg for 50 consecutive" in md


def test_batched_run_equals_per_sequence_runs(bench, tmp_path):
    # The batching machinery is checked with the argmax rule: its whole steps absorb the float32 rounding
    # differences (~1e-8 m) between batch compositions, which the Newton rule's sub-step moves carry on.
    cfg = TrackerConfig().replace(template={"rule": "argmax"})
    opts = dict(methods=["correction_only"], config=cfg, overlays=False, progress=False)
    run_benchmark(bench, tmp_path / "batched", duration_s=DURATION_S, **opts)
    # Alone and for the first half only: the same poses as the first half of the batched run.
    single = run_benchmark(bench, tmp_path / "single", duration_s=DURATION_S / 2, batch=False, **opts)
    assert [r["batch_size"] for r in single["runs"]["correction_only"]] == [1, 1]
    for name in SEQS:
        t1, p1 = read_tum(tmp_path / "single" / "poses" / "correction_only" / f"{name}.txt")
        t2, p2 = read_tum(tmp_path / "batched" / "poses" / "correction_only" / f"{name}.txt")
        assert t1.numel() == N_UPDATES // 2
        t2, p2 = t2[: t1.numel()], p2[: t1.numel()]
        assert torch.equal(t1, t2)
        torch.testing.assert_close(p1, p2, atol=1e-5, rtol=0)


def test_plots_and_overlays_are_images(run, bench):
    res, out = run
    assert res["overlay_method"] == "full"
    for name in SEQS:
        plot = iio.imread(out / "plots" / f"{name}.png")
        assert plot.ndim == 3 and plot.shape[0] > 200 and plot.shape[1] > 300
        assert plot.reshape(-1, plot.shape[-1]).std(0).max() > 10  # not blank
        stills = [iio.imread(out / "overlays" / f"{name}_{k}.png") for k in range(3)]
        for img in stills:
            assert img.shape == (CAM.height, CAM.width, 3) and img.dtype == np.uint8
            assert (img == PRED_COLOUR).all(-1).sum() > 20  # the tracked contour is drawn
        assert sum(int((img == GT_COLOUR).all(-1).sum()) for img in stills) > 0
        gif = iio.imread(out / "overlays" / f"{name}.gif", index=None)
        assert gif.ndim == 4 and gif.shape[0] >= 2 and gif.shape[1:3] == (CAM.height, CAM.width)
        # The last still shows the written trajectory at its last update, over the EROS of that time.
        seq = Sequence.load(bench / name)
        t_us, poses = read_tum(out / "poses" / "full" / f"{name}.txt")
        expected = overlay_frames(seq.events, seq.camera, seq.mesh, (t_us, poses), t_us[-1:],
                                  (seq.gt_t_us, seq.gt_poses))[0]
        np.testing.assert_array_equal(stills[2], expected)
    assert sorted(res["overlays"]) == sorted(SEQS)


def test_sequences_with_different_cameras_run_in_separate_batches(bench, tmp_path):
    root = tmp_path / "bench"
    for name in SEQS:
        shutil.copytree(bench / name, root / name)
    shutil.copytree(bench / "cracker_regular", root / "cracker_other")
    Camera(160, 120, 130.0, 130.0, 79.5, 59.5).save(root / "cracker_other" / "camera.json")
    res = run_benchmark(root, tmp_path / "out", methods=["velocity_only"], duration_s=0.01, overlays=False,
                        progress=False)
    runs = res["runs"]["velocity_only"]
    assert sorted(sorted(r["sequences"]) for r in runs) == [["cracker_other"], ["cracker_regular", "tomato_fast"]]
    assert all(r["updates"] == 5 for r in runs)
    assert res["sequences"]["cracker_other"]["camera"]["fx"] == 130.0
    assert all(v["metrics"]["n_poses"] == 5 for v in res["results"]["velocity_only"].values())


def test_cli_prints_the_table(bench, tmp_path, capsys):
    code = main(["benchmark", str(bench), "--out", str(tmp_path), "--methods", "velocity_only",
                 "--only", "tomato_fast", "--duration", "0.01", "--no-overlays", "--quiet"])
    printed = capsys.readouterr().out
    assert code == 0
    assert printed.startswith((tmp_path / "table.md").read_text())
    rows = _table(printed, "## Pose error")
    assert rows[0] == ["Method", "tomato_fast", "Mean"] and rows[2][0] == METHOD_NAMES["velocity_only"]
    assert not (tmp_path / "overlays").exists() and (tmp_path / "plots" / "tomato_fast.png").is_file()
    # the per-factor report follows the table (factors read from the sequence's own files)
    factors = (tmp_path / "factors.md").read_text()
    assert factors in printed and "## Motion group" in factors and "| fast | velocity_only | 1 |" in factors
    assert (tmp_path / "plots" / "suite_errors.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_arguments_are_rejected(bench, tmp_path, capsys):
    with pytest.raises(ValueError, match="methods"):
        run_benchmark(bench, tmp_path, methods=["full", "ours"])
    with pytest.raises(ValueError, match="only"):
        run_benchmark(bench, tmp_path, only=["mustard_regular"])
    with pytest.raises(ValueError, match="duration_s"):
        run_benchmark(bench, tmp_path, duration_s=0.0)
    with pytest.raises(FileNotFoundError, match="benchmark directory"):
        run_benchmark(tmp_path / "missing", tmp_path)
    with pytest.raises(ValueError, match="shorter than one update"):
        run_benchmark(bench, tmp_path, duration_s=0.001)
    with pytest.raises(ValueError, match="run_benchmark"):
        table_markdown({"nothing": 1})
    assert main(["benchmark", str(bench), "--out", str(tmp_path), "--methods", "nope"]) == 2
    assert "methods" in capsys.readouterr().err


def test_mesh_points_subsample_evenly():
    v = np.random.default_rng(0).normal(size=(2500, 3))
    p = mesh_points(v, 1000)
    assert p.shape == (1000, 3) and p.dtype == torch.float64
    rows = {tuple(r) for r in v.tolist()}
    assert all(tuple(r) in rows for r in p.tolist()) and len({tuple(r) for r in p.tolist()}) == 1000
    assert mesh_points(v).shape == (2000, 3)
    assert torch.equal(p[0], torch.from_numpy(v[0])) and torch.equal(p[-1], torch.from_numpy(v[-1]))
    assert torch.equal(mesh_points(v[:10]), torch.from_numpy(v[:10]))
    with pytest.raises(ValueError, match="vertices"):
        mesh_points(np.zeros((4, 2)))


def test_loss_detection_is_reported_against_the_failure_rule(run, bench, tmp_path):
    res, out = run
    md = (out / "table.md").read_text()
    rows = _table(md, "## Tracking loss")
    assert rows[0] == ["Method", "cracker_regular", "tomato_fast", "detected", "missed", "false alarms",
                       "within 50 ms", "false alarms / min", "recoveries"]
    for m in METHODS:
        for name in SEQS:
            loss, x = res["results"][m][name]["loss"], res["results"][m][name]["metrics"]
            assert set(loss) == {"first_loss_us", "first_failure_us", "delay_us", "missed", "false_alarm",
                                 "declarations", "false_alarms", "recoveries", "tracked_us"}
            assert (loss["first_failure_us"] is not None) == sym_failed(x)
    # A detector that finds every update short of flow declares loss at the first update: with 10 updates
    # nothing can fail (50 needed), so every sequence is a false alarm at t_start + 2 ms.
    cfg = TrackerConfig().replace(loss={"min_flow_vectors": 1000, "patience": 1})
    strict = run_benchmark(bench, tmp_path, methods=["velocity_only"], duration_s=0.02, config=cfg, overlays=False,
                           progress=False)
    for name in SEQS:
        t0 = strict["sequences"][name]["t_start_us"]
        assert strict["results"]["velocity_only"][name]["loss"] == {
            "first_loss_us": t0 + 2000, "first_failure_us": None, "delay_us": None, "missed": False,
            "false_alarm": True, "declarations": 1, "false_alarms": 1, "recoveries": 0, "tracked_us": 18_000}
    rows = _table(table_markdown(strict), "## Tracking loss")
    # two false alarms in 2 x 18 ms of tracking: 2 / (36 ms / 60 s) = 3333.33 per minute
    assert rows[2] == [METHOD_NAMES["velocity_only"], "0.002 / –", "0.002 / –", "0", "0", "2", "0 of 0", "3333.33",
                       "0"]
    assert not strict["config"]["loss"]["enabled"]  # the benchmark runs the detector anyway (it only reports)
    # with two draws the counts pool both (four false alarms in 4 x 18 ms), the cells show the first
    drawn = run_benchmark(bench, tmp_path / "drawn", methods=["velocity_only"], duration_s=0.02, config=cfg,
                          overlays=False, progress=False, init_noise=(0.01, 0.005), trials=2)
    assert all(len(runs) == 2 and all(x["loss"]["false_alarm"] for x in runs)
               for runs in drawn["trials"]["velocity_only"].values())
    rows = _table(table_markdown(drawn), "## Tracking loss")
    assert rows[2] == [METHOD_NAMES["velocity_only"], "0.002 / –", "0.002 / –", "0", "0", "4", "0 of 0", "3333.33",
                       "0"]
    # with recovery on, the lost flags are the recoverer's (held: no recent event pixels are enough for a search
    # here) and each run counts its searches
    held = run_benchmark(bench, tmp_path / "recover", methods=["velocity_only"], duration_s=0.02, overlays=False,
                         config=cfg.replace(loss={"enabled": True},
                                            recover={"enabled": True, "min_events": 10 ** 9}), progress=False)
    assert [(r["searches"], r["restarts"]) for r in held["runs"]["velocity_only"]] == [(0, 0)]
    for name in SEQS:
        assert held["results"]["velocity_only"][name]["loss"] == strict["results"]["velocity_only"][name]["loss"]


def test_table_lists_the_rotation_error_modulo_symmetry_for_symmetric_objects(run):
    res = copy.deepcopy(run[0])
    assert "modulo the symmetry axis" not in table_markdown(res)  # the built-in can is textured: no axis
    res["sequences"]["tomato_fast"]["symmetry_axis"] = [0.0, 0.0, 1.0]
    for i, meth in enumerate(METHODS):
        res["results"][meth]["tomato_fast"]["metrics"].update(rmse_r_sym_deg=1.5 + i, std_r_sym_deg=0.25,
                                                              failed_sym=meth == "full")
    rows = _table(table_markdown(res), "## Rotation error modulo the symmetry axis")
    assert rows[0] == ["Method", "tomato_fast"]
    got = {r[0]: r[1] for r in rows[2:]}
    assert got == {METHOD_NAMES["correction_only"]: "2.50(0.25)", METHOD_NAMES["full"]: "1.50(0.25)†"}


def test_trials_start_from_perturbed_poses_and_report_their_spread(bench, tmp_path):
    res = run_benchmark(bench, tmp_path, methods=["velocity_only", "correction_only"], duration_s=0.01,
                        init_noise=(3.0, 2.0), trials=2, seed=5, overlays=False, progress=False)
    noise = res["init_noise"]
    assert (noise["translation_mm"], noise["rotation_deg"], noise["trials"], noise["seed"]) == (3.0, 2.0, 2, 5)
    for k in range(2):
        for name in SEQS:
            gt0 = Sequence.load(bench / name).gt_poses[0].double()
            start = torch.tensor(noise["start_poses"][k][name], dtype=torch.float64)
            assert abs(float((start[:3] - gt0[:3]).norm()) - 0.003) < 1e-6
            dot = float((start[3:] * gt0[3:]).sum().abs().clamp(max=1.0))
            assert abs(math.degrees(2 * math.acos(dot)) - 2.0) < 1e-3
    assert noise["start_poses"][0] != noise["start_poses"][1]
    # oracle: the tracker itself, one batch from the first trial's start poses (the benchmark's sequence order)
    seqs = [Sequence.load(bench / name) for name in sorted(SEQS)]
    cfg = TrackerConfig().replace(**ABLATIONS["velocity_only"], loss={"enabled": True})
    tracker = EventPoseTracker(CAM, [str(bench / name / "mesh.ply") for name in sorted(SEQS)], cfg)
    t0 = [int(s.gt_t_us[0]) for s in seqs]
    _, poses = tracker.track([s.events for s in seqs],
                             torch.tensor([noise["start_poses"][0][name] for name in sorted(SEQS)]),
                             t_start_us=t0, t_end_us=[t + 10_000 for t in t0], progress=False)
    for i, name in enumerate(sorted(SEQS)):
        _, written = read_tum(tmp_path / "poses" / "velocity_only" / f"{name}.txt")
        torch.testing.assert_close(written, poses[i].double(), atol=1e-6, rtol=0)
    for method in ("velocity_only", "correction_only"):
        for name in SEQS:
            trials = res["trials"][method][name]
            assert len(trials) == 2
            assert trials[0]["rmse_t_cm"] == res["results"][method][name]["metrics"]["rmse_t_cm"]
            s = Sequence.load(bench / name)
            t_us, p = read_tum(tmp_path / "poses" / method / "trial1" / f"{name}.txt")
            m = evaluate(t_us, p, s.gt_t_us, s.gt_poses, mesh_points=_independent_points(s.mesh))
            assert trials[1]["rmse_t_cm"] == pytest.approx(m["rmse_t_cm"], abs=1e-9)
            assert trials[1]["adds_auc"] == pytest.approx(m["adds_auc"], abs=1e-9)
            assert trials[1]["failed"] == m["failed"]
    rows = _table(table_markdown(res), "## Start poses perturbed by 3 mm and 2 deg: 2 trials (seed 5)")
    head = rows[0].index("Mean e_p (cm)")
    sym = any("failed_sym" in x for runs in res["trials"].values() for seq in runs.values() for x in seq)
    assert rows[0][head:] == ["Mean e_p (cm)", "Median e_p (cm)", "Mean e_r (deg)", "ADD-S AUC (%)", "failed runs"] \
        + (["Mean e_r, sym. (deg)", "failed runs, sym."] if sym else [])
    ours = dict(zip(rows[0], next(r for r in rows if r[0] == METHOD_NAMES["velocity_only"])))
    trials = res["trials"]["velocity_only"]
    per_trial = [np.mean([trials[c][k]["rmse_t_cm"] for c in SEQS]) for k in range(2)]
    assert ours["Mean e_p (cm)"] == f"{np.mean(per_trial):.2f} ± {np.std(per_trial):.2f}"
    assert ours["Median e_p (cm)"] == f"{np.median([x['rmse_t_cm'] for c in SEQS for x in trials[c]]):.2f}"
    assert ours["failed runs"] == f"{sum(x['failed'] for c in SEQS for x in trials[c])}/{2 * len(SEQS)}"
    assert not sym and "failed runs, sym." not in rows[0]  # neither test object is symmetric untextured
    # a symmetric object's run: the table adds its error and failures with the spin left out, the others' whole
    sym_res = copy.deepcopy(res)
    for k, x in enumerate(sym_res["trials"]["velocity_only"]["tomato_fast"]):
        x.update(rmse_r_sym_deg=x["rmse_r_deg"] / (k + 2), failed_sym=not x["failed"])
    sym_rows = _table(table_markdown(sym_res), "## Start poses perturbed by 3 mm and 2 deg: 2 trials (seed 5)")
    ours = dict(zip(sym_rows[0], next(r for r in sym_rows if r[0] == METHOD_NAMES["velocity_only"])))
    can, box = sym_res["trials"]["velocity_only"]["tomato_fast"], trials["cracker_regular"]
    assert ours["failed runs, sym."] == f"{sum(not x['failed'] for x in can) + sum(x['failed'] for x in box)}/4"
    r_sym = [np.mean([can[k]["rmse_r_deg"] / (k + 2), box[k]["rmse_r_deg"]]) for k in range(2)]
    assert ours["Mean e_r, sym. (deg)"] == f"{np.mean(r_sym):.2f} ± {np.std(r_sym):.2f}"


def test_trial_arguments_are_checked(bench, tmp_path, capsys):
    with pytest.raises(ValueError, match="needs init_noise"):
        run_benchmark(bench, tmp_path, trials=2)
    with pytest.raises(ValueError, match="init_noise"):
        run_benchmark(bench, tmp_path, init_noise=(-1.0, 0.0))
    with pytest.raises(ValueError, match="trials"):
        run_benchmark(bench, tmp_path, init_noise=(1.0, 1.0), trials=0)
    with pytest.raises(SystemExit) as exit_:
        main(["benchmark", str(bench), "--out", str(tmp_path), "--init-noise", "1"])
    assert exit_.value.code == 2 and "MM,DEG" in capsys.readouterr().err


def _foreign_poses(seq: Sequence, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Another tracker's output: the ground truth at 100 Hz, off by a few mm and a degree or two, from before the
    sequence start (those poses are dropped) to its end."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(int(seq.gt_t_us[0]) - 20_000, int(seq.gt_t_us[-1]) + 1, 10_000)
    from torchevtrack.geometry import interpolate_poses, quat_exp, quat_mul

    gt = interpolate_poses(seq.gt_t_us, seq.gt_poses, t.clamp(int(seq.gt_t_us[0]), int(seq.gt_t_us[-1])))
    dq = quat_exp(torch.randn(len(t), 3, generator=g, dtype=torch.float64) * 0.02)
    return t, torch.cat((gt[:, :3] + 0.004 * torch.randn(len(t), 3, generator=g, dtype=torch.float64),
                         quat_mul(dq, gt[:, 3:])), dim=-1)


def test_foreign_predictions_are_scored_as_eval_scores_them(bench, tmp_path, capsys):
    from torchevtrack.io.poses import write_poses

    learned = tmp_path / "learned"
    learned.mkdir()
    for i, (name, ext) in enumerate((("cracker_regular", ".txt"), ("tomato_fast", ".csv"))):
        write_poses(learned / f"{name}{ext}", *_foreign_poses(Sequence.load(bench / name), i))
    out = tmp_path / "out"
    assert main(["benchmark", str(bench), "--out", str(out), "--methods", "velocity_only", "--no-overlays", "--quiet",
                 "--pred", f"learned={learned}"]) == 0
    printed = capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    assert set(res["results"]) == {"velocity_only", "learned"}
    for name, ext in (("cracker_regular", ".txt"), ("tomato_fast", ".csv")):
        assert main(["eval", "--gt", str(bench / name), "--pred", str(learned / f"{name}{ext}"), "--json"]) == 0
        by_eval = json.loads(capsys.readouterr().out)
        got = res["results"]["learned"][name]["metrics"]
        assert by_eval["n_dropped"] == 2 and by_eval["n_mesh_points"] == res["sequences"][name]["mesh_points"]
        for k, v in by_eval.items():  # every key eval prints, with the same value
            if k != "n_mesh_points":
                assert got[k] == v, (name, k)
    rows = {r[0]: r for r in _table(printed, "## Pose error")}
    assert "learned" in rows and CELL.match(rows["learned"][1].rstrip("†"))
    assert "learned" in {r[0] for r in _table(printed, "## ADD-S AUC")}
    assert "learned" not in {r[0] for r in _table(printed, "## Tracking loss")}  # no lost-flag side files
    assert "| learned |" in (out / "factors.md").read_text()  # the per-factor tables too


def test_the_lost_flags_are_written_and_scored_again_from_their_side_files(run, bench, tmp_path):
    """Every run's lost flags go beside its pose file; given as another tracker's poses (``--pred``), the files
    give the loss table the run itself gave."""
    from torchevtrack.io.lost import lost_path, read_lost

    res, out = run
    for name in SEQS:
        r = res["results"]["full"][name]
        t_us, _ = read_tum(out / r["pose_file"])
        lost_t, lost = read_lost(lost_path(out / r["pose_file"]))
        assert torch.equal(lost_t, t_us) and lost.dtype == torch.bool
    again = run_benchmark(bench, tmp_path, methods=["velocity_only"], overlays=False, progress=False,
                          predictions={"ours": out / "poses" / "full"})
    for name in SEQS:
        assert again["results"]["ours"][name]["loss"] == res["results"]["full"][name]["loss"]
    rows = {r[0]: r[1:] for r in _table(table_markdown(again), "## Tracking loss")}
    mine = {r[0]: r[1:] for r in _table(table_markdown(res), "## Tracking loss")}
    assert rows["ours"] == mine[METHOD_NAMES["full"]]
    bad = tmp_path / "bad"
    shutil.copytree(out / "poses" / "full", bad)
    lost_path(bad / "tomato_fast.txt").write_text("0.5 1\n")
    with pytest.raises(ValueError, match="tomato_fast.lost.txt: its times"):
        run_benchmark(bench, tmp_path / "b", methods=["velocity_only"], duration_s=0.02, overlays=False,
                      progress=False, predictions={"ours": bad})


def test_foreign_prediction_errors(bench, tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="cracker_regular.txt"):
        run_benchmark(bench, tmp_path, methods=["velocity_only"], duration_s=0.01, overlays=False, progress=False,
                      predictions={"learned": tmp_path})
    with pytest.raises(ValueError, match="prediction name"):
        run_benchmark(bench, tmp_path, methods=["velocity_only"], predictions={"full": tmp_path})
    with pytest.raises(SystemExit):
        main(["benchmark", str(bench), "--out", str(tmp_path), "--pred", "learned"])
    assert "NAME=DIR" in capsys.readouterr().err
    assert main(["benchmark", str(bench), "--out", str(tmp_path), "--pred", f"a={tmp_path}", "--pred",
                 f"a={tmp_path}"]) == 2
    assert "more than once" in capsys.readouterr().err


def test_textured_tracks_a_printed_object_with_its_textured_model(bench, tmp_path):
    """``textured=True``: a sequence with its printed model is tracked with that model (the poses of a tracker given
    the model directly), one without it with ``mesh.ply`` as before; the scoring is the same."""
    from torchevtrack.synth.sequence import TEXTURED_MESH

    root = tmp_path / "bench"
    generate_sequence("box", "turn", DURATION_S, seed=5, camera=CAM, texture="random",
                      progress=False).save(root / "printed_turn")
    shutil.copytree(bench / "tomato_fast", root / "tomato_fast")
    assert (root / "printed_turn" / TEXTURED_MESH).is_file() and not (root / "tomato_fast" / TEXTURED_MESH).exists()
    kw = dict(methods=("no_ukf",), overlays=False, progress=False)
    plain, printed = (run_benchmark(root, tmp_path / name, textured=t, **kw) for name, t in (("a", False), ("b", True)))
    assert not plain["textured"] and printed["textured"]
    assert {k: v["mesh"] for k, v in printed["sequences"].items()} == {"printed_turn": TEXTURED_MESH,
                                                                        "tomato_fast": "mesh.ply"}
    assert "textured models" in table_markdown(printed) and "textured models" not in table_markdown(plain)

    def poses(res, out, name):
        return read_tum(out / res["results"]["no_ukf"][name]["pose_file"])[1]

    assert torch.equal(poses(plain, tmp_path / "a", "tomato_fast"), poses(printed, tmp_path / "b", "tomato_fast"))
    seq = Sequence.load(root / "printed_turn")
    tracker = EventPoseTracker(CAM, str(root / "printed_turn" / TEXTURED_MESH))
    try:
        _, direct = tracker.track(seq.events, seq.gt_poses[0], t_start_us=int(seq.gt_t_us[0]),
                                  t_end_us=int(seq.gt_t_us[-1]), progress=False)
    finally:
        tracker.close()
    got = poses(printed, tmp_path / "b", "printed_turn")
    assert torch.allclose(got, direct[0].to(got.dtype), atol=1e-5)  # (a batch of two: float32 rounding)
    assert not torch.allclose(got, poses(plain, tmp_path / "a", "printed_turn"), atol=1e-4)
