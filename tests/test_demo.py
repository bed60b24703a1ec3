"""`torchevtrack demo`: the README's first command, end to end on a short sequence."""
import json
import math

import torch

from torchevtrack.cli import main
from torchevtrack.io.poses import read_tum
from torchevtrack.metrics import evaluate
from torchevtrack.synth.sequence import Sequence


def test_demo_writes_a_sequence_poses_metrics_and_an_overlay_that_agree(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--duration", "0.1", "--quiet"]) == 0
    printed = capsys.readouterr().out
    seq = Sequence.load(out / "sequence")
    assert f"{len(seq.events)} events" in printed
    metrics = json.loads((out / "metrics.json").read_text())
    # the metrics are those of the written poses against the written ground truth (scored again here)
    times, poses = read_tum(out / "poses.txt")
    assert len(times) == metrics["n_poses"] >= 45  # 0.1 s at 500 updates/s
    again = evaluate(times, poses, seq.gt_t_us, seq.gt_poses,
                     mesh_points=torch.as_tensor(seq.mesh.vertices[:: max(1, len(seq.mesh.vertices) // 1000)]))
    for key in ("rmse_t_cm", "rmse_r_deg", "add_auc"):
        assert math.isfinite(metrics[key]) and math.isclose(again[key], metrics[key], rel_tol=1e-6, abs_tol=1e-9)
    assert f"translation RMSE {metrics['rmse_t_cm']:.2f} cm" in printed
    assert (out / "overlay.gif").read_bytes()[:4] == b"GIF8"
