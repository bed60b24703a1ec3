"""``torchevtrack bench`` on a tiny generated sequence directory."""

import json

import pytest
import torch

from torchevtrack.camera import Camera
from torchevtrack.cli import main
from torchevtrack.config import TrackerConfig
from torchevtrack.synth.generate import generate_sequence

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)


@pytest.fixture(scope="module")
def seqdir(tmp_path_factory):
    seq = generate_sequence("box", "regular", 0.03, seed=2, camera=CAM, progress=False)
    return seq, seq.save(tmp_path_factory.mktemp("bench") / "box_regular")


@pytest.fixture(autouse=True)
def _restore_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def test_bench_json(seqdir, capsys):
    seq, d = seqdir
    assert main(["bench", str(d), "--duration", "0.02", "--batch", "2", "--warmup", "2", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    t0 = int(seq.gt_t_us[0])
    assert r["n_updates"] == 10 and r["period_us"] == 2000 and r["duration_s"] == pytest.approx(0.02)
    assert r["n_events"] == int(((seq.events.t >= t0) & (seq.events.t < t0 + 20_000)).sum())
    assert r["updates_per_s"] == pytest.approx(r["n_updates"] / r["wall_s"])
    assert r["events_per_s"] == pytest.approx(r["n_events"] / r["wall_s"])
    assert r["realtime_factor"] == pytest.approx(0.02 / r["wall_s"])
    assert 0 < r["p50_ms"] <= r["p99_ms"] <= r["latency_max_ms"]
    assert set(r["stage_ms"]) == {"eros", "flow", "velocity", "render", "correction", "ukf"}
    assert all(v >= 0 for v in r["stage_ms"].values())
    # Each latency contains the stages of its update: their mean sum cannot exceed the largest latency.
    assert r["update_ms"] <= r["latency_max_ms"]
    b = r["batched"]
    assert r["batch"] == b["sequences"] == 2
    assert b["sequential_wall_s"] == pytest.approx(2 * r["offline"]["wall_s"])
    assert r["batched_speedup"] == pytest.approx(b["sequential_wall_s"] / b["wall_s"])
    assert b["updates_per_s"] == pytest.approx(2 * 10 / b["wall_s"])
    m = r["machine"]
    assert m["torch_threads"] == 1 and m["torch"] == torch.__version__ and m["cpu_count"] >= 1
    assert r["offline"]["pipeline"] == (m["cpus_available"] > 1)  # one sequence on two cores: pipelined
    assert TrackerConfig.from_dict(r["config"]) == TrackerConfig()  # the tracker's settings, for the record


def test_bench_repeat_reports_medians_and_pooled_latencies(seqdir, capsys):
    """--repeat 3: three streaming and three offline runs; the headline figures are their medians."""
    _, d = seqdir
    assert main(["bench", str(d), "--duration", "0.01", "--batch", "1", "--warmup", "1", "--repeat", "3",
                 "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    runs = r["runs"]
    assert r["repeat"] == 3 and all(len(v) == 3 for v in runs.values())
    assert r["updates_per_s"] == pytest.approx(sorted(runs["updates_per_s"])[1])
    assert r["updates_per_s"] == pytest.approx(r["n_updates"] / r["wall_s"])
    assert r["offline"]["updates_per_s"] == pytest.approx(sorted(runs["offline_updates_per_s"])[1])
    assert 0 < r["p50_ms"] <= r["p99_ms"] <= r["latency_max_ms"]
    assert r["latency_max_ms"] >= max(runs["p99_ms"])  # the maximum over all the runs' updates
    assert main(["bench", str(d), "--duration", "0.01", "--batch", "1", "--warmup", "0", "--repeat", "2"]) == 0
    assert "medians of 2 runs" in capsys.readouterr().out


def test_bench_summary_and_ablation(seqdir, capsys):
    _, d = seqdir
    assert main(["bench", str(d), "--duration", "0.01", "--batch", "1", "--warmup", "0",
                 "--ablation", "no_ukf", "--threads", "2"]) == 0
    text = capsys.readouterr().out
    assert "(no_ukf): 5 updates" in text and "updates/s" in text and "p99" in text
    assert "batch of" not in text  # --batch 1 skips the batched measurement
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize("argv, message", [
    (["--batch", "0"], "--batch must be >= 1"),
    (["--repeat", "0"], "--repeat must be >= 1"),
    (["--duration", "-1"], "--duration must be positive"),
    (["--duration", "0.001"], "shorter than one update period"),
])
def test_bench_bad_arguments(seqdir, capsys, argv, message):
    _, d = seqdir
    assert main(["bench", str(d), *argv]) == 2
    assert message in capsys.readouterr().err


def test_bench_missing_directory(tmp_path, capsys):
    assert main(["bench", str(tmp_path / "nope"), "--json"]) == 2
    assert "not found" in capsys.readouterr().err


def test_the_packets_cover_the_events_once_in_order(seqdir):
    """The streaming measurement's packets: consecutive chunk_us slices of [t0, t_end), every event in one."""
    from torchevtrack.cli.bench import packets

    seq, _ = seqdir
    t0, t_end = int(seq.events.t[0]) + 50, int(seq.events.t[0]) + 7_300
    got = packets(seq.events, t0, t_end, 1000)
    assert len(got) == 8  # 7 full packets and the last 250 us
    assert torch.equal(torch.cat([p.t for p in got]), seq.events.slice_time(t0, t_end).t)
    assert all(int(p.t.min()) >= t0 + 1000 * k and int(p.t.max()) < min(t0 + 1000 * (k + 1), t_end)
               for k, p in enumerate(got) if len(p))


def test_bench_a_recording_in_another_format_from_a_given_start(seqdir, tmp_path, capsys):
    """A directory with only camera.json: --events (text), --mesh and --init, the start at the first event."""
    import shutil

    from torchevtrack.io.formats import write_events

    seq, d = seqdir
    bare = tmp_path / "rec"
    bare.mkdir()
    shutil.copy(d / "camera.json", bare / "camera.json")
    write_events(tmp_path / "ev.txt", seq.events, width=CAM.width, height=CAM.height)
    p = seq.gt_poses[0].tolist()
    init = " ".join(f"{a:.9f}" for a in p[:3] + p[4:] + p[3:4])  # TUM order, qw last
    args = ["bench", str(bare), "--duration", "0.01", "--batch", "1", "--warmup", "0", "--json"]
    assert main(args + ["--events", str(tmp_path / "ev.txt"), "--mesh", str(d / "mesh.ply"), "--init", init]) == 0
    r = json.loads(capsys.readouterr().out)
    t0 = int(seq.events.t[0])
    assert r["n_updates"] == 5 and r["n_events"] == int(((seq.events.t >= t0) & (seq.events.t < t0 + 10_000)).sum())
    assert main(args + ["--events", str(tmp_path / "ev.txt"), "--mesh", str(d / "mesh.ply")]) == 2
    assert "has no gt_poses.txt: give the initial pose with --init" in capsys.readouterr().err
