"""Smoke tests of tools/: every tool parses its arguments, and those that take a sequence run on a tiny one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
TOOLS = sorted((ROOT / "tools").glob("*.py"))
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}


def _run(*args: str, timeout: float = 600) -> str:
    done = subprocess.run([sys.executable, *args], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


@pytest.mark.parametrize("tool", TOOLS, ids=[t.name for t in TOOLS])
def test_help(tool: Path) -> None:
    assert "usage" in _run(str(tool), "--help", timeout=120)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tools") / "can"
    _run("-m", "torchevtrack", "synth", "--object", "can", "--motion", "regular", "--duration", "0.06", "--seed", "1",
         "--width", "160", "--height", "120", "--fx", "125", "--fy", "125", "--out", str(out), "--quiet")
    return out


def test_overlay_frame(sequence: Path, tmp_path: Path) -> None:
    png = tmp_path / "overlay.png"
    _run("tools/overlay_frame.py", str(sequence), "--time", "0.03", "--out", str(png))
    assert png.stat().st_size > 0


def test_profile_update(sequence: Path) -> None:
    assert "forward" in _run("tools/profile_update.py", str(sequence), "--duration", "0.04", "--passes", "1")


def test_bench_flow(sequence: Path) -> None:
    assert _run("tools/bench_flow.py", "--seq", str(sequence), "--duration", "0.04", "--repeat", "1").strip()


def test_oracle_split(sequence: Path, tmp_path: Path) -> None:
    """The true twist integrated without the correction follows the truth (the oracle checks itself); the estimated
    and true-twist modes run and report every sequence."""
    out = tmp_path / "oracle.json"
    _run("tools/oracle_split.py", str(sequence.parent), "--duration", "0.05", "--json", str(out))
    r = json.loads(out.read_text())
    assert set(r) == {"estimated", "true-twist", "true-twist-only"}
    assert all(list(m) == [sequence.name] for m in r.values())
    only = r["true-twist-only"][sequence.name]
    assert only["rmse_t_cm"] < 0.1 and only["rmse_r_deg"] < 0.2 and not only["failed"]


def test_diagnose_loss_oracle(sequence: Path) -> None:
    lines = _run("tools/diagnose_loss.py", str(sequence), "--duration", "0.04", "--every", "5",
                 "--oracle-velocity").splitlines()
    assert len(lines) >= 4 and lines[2].split()[0] == "2.0"


def test_diagnose_loss_twist(sequence: Path) -> None:
    """With the true twist put into the filter, ``--twist`` reads it back (its RMS against the truth near zero: the
    state is the twist about the centre, as the oracle's); from the flow it is off by more."""
    def rms(*extra: str) -> list[float]:
        lines = _run("tools/diagnose_loss.py", str(sequence), "--duration", "0.04", "--every", "5", "--twist",
                     *extra).splitlines()
        assert lines[1].split()[7:19] == [f"{q}{a}_{k}" for q in "vw" for k in ("est", "gt") for a in "xyz"]
        assert len(lines[2].split()) == 21  # time, 6 errors, 12 rates, 2 error norms
        last = lines[-1].replace(",", " ").split()
        assert last[:8] == ["RMS", "twist", "error", "velocity", "filter", "against", "the", "truth:"]
        return [float(v) for v in last[9:12] + last[14:17]]

    oracle, flow = rms("--oracle-velocity"), rms()
    assert max(oracle[:3]) < 0.1 and max(oracle[3:]) < 5  # cm/s, deg/s
    assert sum(flow) > sum(oracle) + 10


def test_recovery_trials(sequence: Path) -> None:
    """A start at the truth is counted within the bounds one update later (and reached them at that first update,
    as the reference run from the truth did), a start 5 cm off is not and never reached them (20 ms cannot close
    that; the run from the truth is within 3 cm); a blackout trial reports the error before the gap and is
    judged after it (loose bounds: this tiny 160x120 sequence drifts ~4 cm in 60 ms). With the UKF, as these figures
    were set (without it the run from the truth drifts past 3 cm by 20 ms)."""
    args = ("tools/recovery_trials.py", str(sequence.parent), "--set", "ukf.enabled=true", "--mode")  # as measured
    near = _run(*args, "start", "--draws", "2", "--offset-mm", "0", "--offset-deg", "0", "--settle", "0.002")
    assert "start: 2 of 2 within" in near and near.count(" ok") == 3
    assert near.count("reached     2 ms") == 2 and "2 of 2 reached them by then" in near
    assert "started at the truth: 1 of 1 sequences within them" in near
    far = _run(*args, "start", "--draws", "1", "--offset-mm", "50", "--offset-deg", "0", "--settle", "0.02",
               "--max-cm", "3", "--max-deg", "10")  # the run from the truth drifts 2 cm by then
    assert "start: 0 of 1 within" in far and "MISS" in far and "reached never" in far
    assert "0 of 1 reached them by then" in far and "started at the truth: 1 of 1" in far
    gap = _run(*args, "blackout", "--at", "0.02", "--gap-ms", "10", "--settle", "0.02", "--max-cm", "50",
               "--max-deg", "90")
    assert "before" in gap and "blackout: 1 of 1 within" in gap
    # how far the object moved in the gap, against the ground truth read here
    import torch

    from torchevtrack.geometry import interpolate_poses
    from torchevtrack.synth.sequence import Sequence

    seq = Sequence.load(sequence)
    t0 = int(seq.gt_t_us[0])
    ends = interpolate_poses(seq.gt_t_us, seq.gt_poses, torch.tensor([t0 + 20_000, t0 + 30_000]))
    moved = float((ends[1, :3] - ends[0, :3]).norm()) * 100.0
    printed = float(gap.split(" moved ")[1].split()[0])
    assert abs(printed - moved) <= 0.051 and 0.5 < moved <= 10.0  # (0.9 cm in these 10 ms)
    assert "at most 10 cm in the gap (issue 25's trials): 1 of 1" in gap
    # the reference tracks the same sequence without the gap, in the same batch
    assert gap.count("without the gap  after") == 1 and "without the gap: 1 of 1 counted trials within them" in gap
    assert "0 of the 0 misses miss without the gap too" in gap


def test_hand_oracle(sequence: Path, tmp_path: Path) -> None:
    import trimesh

    from torchevtrack.render import DEFAULT_ALBEDO

    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "can").symlink_to(sequence)  # no hand: left out
    _run("-m", "torchevtrack", "synth", "--object", "can", "--motion", "regular", "--duration", "0.03", "--seed", "1",
         "--width", "160", "--height", "120", "--fx", "125", "--fy", "125", "--occluder", "hand",
         "--out", str(suite / "held"), "--quiet")
    plain = trimesh.load(suite / "held" / "mesh.ply", force="mesh")  # the built-in can is coloured: a plain one
    trimesh.Trimesh(plain.vertices, plain.faces).export(suite / "held" / "mesh.ply")
    out = tmp_path / "grip"
    _run("tools/hand_oracle.py", str(suite), "--out", str(out))
    assert sorted(p.name for p in out.iterdir()) == ["held"]
    obj = trimesh.load(suite / "held" / "mesh.ply", force="mesh")
    union = trimesh.load(out / "held" / "mesh.ply", force="mesh")
    a = int(np.argmax(obj.extents))  # the grip's axis: the palm, 2 cm thick, lies against the -a end face
    assert union.bounds[0, a] == pytest.approx(obj.bounds[0, a] - 0.02, abs=1e-6)
    assert union.bounds[1, a] == pytest.approx(obj.bounds[1, a], abs=1e-6)  # the fingers stop short of the far end
    assert obj.visual.kind is None and union.visual.kind == "vertex"  # painted the renderers' grey
    grey = round(DEFAULT_ALBEDO * 255)
    assert (union.visual.vertex_colors[:, :3] == grey).all(1).sum() >= len(obj.vertices)
    assert (out / "held" / "events.h5").resolve() == (suite / "held" / "events.h5").resolve()
    done = subprocess.run([sys.executable, "tools/hand_oracle.py", str(sequence), "--out", str(tmp_path / "x")],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "no sequence with a hand" in done.stderr
    obj.apply_scale(1.1)  # another mesh than the one the hand was built from: refused
    obj.export(suite / "held" / "mesh.ply")
    done = subprocess.run([sys.executable, "tools/hand_oracle.py", str(suite), "--out", str(tmp_path / "y")],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "does not reproduce" in done.stderr and len(done.stderr.splitlines()) == 1


def test_recovery_trials_away(tmp_path: Path) -> None:
    """Away mode judges a ``synth --leave-view`` sequence ``--settle`` after the object is back (0.1 + 0.2 + 0.7 s
    here), reports the error before it left, and refuses a sequence made without an excursion."""
    from torchevtrack.cli import main

    tiny = ["--width", "64", "--height", "48", "--fx", "50", "--fy", "50", "--quiet"]
    assert main(["synth", "--object", "box", "--duration", "1.1", "--leave-view", "0.1,0.2", "--out",
                 str(tmp_path / "bench" / "away"), *tiny]) == 0
    out = _run("tools/recovery_trials.py", str(tmp_path / "bench"), "--mode", "away", "--settle", "0.05",
               "--max-cm", "100", "--max-deg", "180", "--set", "loss.enabled=true", "--set", "recover.enabled=true")
    # the toy's outcome is chaotic (within 1 m on one build of its kernels, 1.36 m off on another): the verdict must
    # follow the printed error
    words = out.split()
    assert words[:3] == ["away", "0", "before"], out
    after = words.index("after")
    ok = float(words[after + 1]) <= 100.0 and float(words[after + 3]) <= 180.0
    assert words[words.index("flags") + 2] == ("ok" if ok else "MISS"), out
    assert f"away: {int(ok)} of 1 within 100.0 cm / 180.0 deg" in out, out
    assert "(0 trials off before it left, not counted)" in out and "without the gap" not in out
    assert main(["synth", "--object", "box", "--duration", "0.05", "--out", str(tmp_path / "plain" / "p"), *tiny]) == 0
    done = subprocess.run([sys.executable, "tools/recovery_trials.py", str(tmp_path / "plain"), "--mode", "away"],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
    assert done.returncode != 0 and "not a sequence made with synth --leave-view" in done.stderr


def _tool(name: str):
    """A tool's module, imported from its file (tools/ is no package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_depth_check_curve_replays_the_flag():
    """A run failing at 100 ms whose rival x 0.8 is 1 px cheaper from 120 ms on: a check every 10 ms flags it within
    50 ms, one every 50 ms only at 150 ms (still within), one every 80 ms at 160 ms (not within); a margin of 2 px
    never; the rival x 1.25 never. A run that never fails, flagged at 20-30 ms only: one false alarm."""
    curve = _tool("depth_check_curve")
    rows = [[t * 1000, 5.0, 4.0 if t >= 120 else 6.0, 7.0] for t in range(10, 400, 10)]
    held = [[t * 1000, 5.0, 4.0 if t in (20, 30) else 6.0, 7.0] for t in range(10, 400, 10)]
    runs = {"lost": {"t0": 0, "fail": 100_000, "rows": rows}, "held": {"t0": 0, "fail": None, "rows": held}}
    minutes = (0.1 + 0.39) / 60
    r = curve.replay(runs, [2], 10_000, 0.5)
    assert (r["failed"], r["within"], r["flagged"]) == (1, 1, 1) and r["false_per_min"] == pytest.approx(1 / minutes)
    assert curve.replay(runs, [2], 50_000, 0.5)["within"] == 1
    r = curve.replay(runs, [2], 80_000, 0.5)
    assert (r["within"], r["flagged"], r["false_per_min"]) == (0, 1, 0.0)  # 80 ms checks miss the held run's flag
    assert curve.replay(runs, [2], 10_000, 2.0)["flagged"] == 0
    assert curve.replay(runs, [3], 10_000, 0.5)["flagged"] == 0


def test_depth_check_curve_on_a_benchmark(sequence: Path, tmp_path: Path) -> None:
    out = tmp_path / "bench"
    _run("-m", "torchevtrack", "benchmark", str(sequence.parent), "--out", str(out), "--methods", "no_ukf",
         "--no-overlays", "--quiet")
    table = _run("tools/depth_check_curve.py", str(out), str(sequence.parent), "--subsets", "0.8,1.25",
                 "--periods", "10,20", "--margins", "0.5", "--save", str(tmp_path / "costs.json"))
    rows = [line for line in table.splitlines() if line.startswith("| x 0.8")]
    assert len(rows) == 2 and all(r.split("|")[4].strip() == "0" for r in rows)  # 0.06 s: nothing fails
    costs = json.loads((tmp_path / "costs.json").read_text())[f"{out}/{sequence.name}"]["rows"]
    assert len(costs) == 6 and all(len(r) == 6 for r in costs)  # every 10 ms of 60: [t, own, 4 rivals]
    done = subprocess.run([sys.executable, "tools/depth_check_curve.py", str(out)], cwd=ROOT, env=ENV,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "OUT DATA [OUT DATA ...]" in done.stderr
