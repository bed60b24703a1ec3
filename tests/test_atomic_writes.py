"""No writer loses data: an output is replaced only when its write succeeded. A failing input, an exception
or a killed process leaves an existing file byte for byte as it was."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchevtrack.cli import main
from torchevtrack.events import EventStream
from torchevtrack.io.formats import write_events
from torchevtrack.io.poses import write_csv, write_tum

ROOT = Path(__file__).resolve().parents[1]


def _events(n=3000):
    rng = np.random.default_rng(0)
    return EventStream.from_arrays(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 10**6, n)),
                                   rng.integers(0, 2, n))


@pytest.mark.parametrize("suffix", [".h5", ".npz", ".txt"])
def test_convert_keeps_a_good_output_when_the_input_fails_midway(tmp_path, suffix, capsys):
    good = tmp_path / f"out{suffix}"
    write_events(good, _events())
    before = good.read_bytes()
    src = tmp_path / "in.txt"
    lines = [f"{t} {t % 64} {t % 48} {t % 2}" for t in range(0, 5000, 2)]
    lines.insert(2000, "1 2 3 not-a-number")
    src.write_text("\n".join(lines) + "\n")
    assert main(["convert", str(src), str(good), "--chunk", "100", "--quiet"]) == 2
    assert "line 2001" in capsys.readouterr().err
    assert good.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["in.txt", good.name])  # no temporary left


def test_convert_into_a_directory_fails_before_reading(tmp_path, capsys):
    src = tmp_path / "in.txt"
    src.write_text("0 1 1 1\n5 2 2 0\n")
    (tmp_path / "d.h5").mkdir()
    assert main(["convert", str(src), str(tmp_path / "d.h5"), "--quiet"]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_a_killed_writer_leaves_the_old_file(tmp_path):
    """SIGKILL in the middle of writing an events.h5 over a good one: the good one is intact."""
    good = tmp_path / "events.h5"
    write_events(good, _events())
    before = good.read_bytes()
    script = (
        "import os, signal, numpy as np\n"
        "from torchevtrack.events import EventStream\n"
        "from torchevtrack.io.events_h5 import EventsH5Writer\n"
        "def chunks():\n"
        "    for k in range(100):\n"
        "        if k == 3:\n"
        "            os.kill(os.getpid(), signal.SIGKILL)\n"
        "        n = 100000\n"
        "        yield EventStream.from_arrays(np.zeros(n, int), np.zeros(n, int), np.arange(k * n, (k + 1) * n), "
        "np.ones(n, int))\n"
        f"with EventsH5Writer({str(good)!r}) as w:\n"
        "    for c in chunks():\n"
        "        w.append(c)\n"
    )
    r = subprocess.run([sys.executable, "-c", script], env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)
    assert r.returncode == -signal.SIGKILL
    assert good.read_bytes() == before


@pytest.mark.parametrize("writer", [write_tum, write_csv])
def test_pose_writers_replace_only_on_success(tmp_path, writer):
    path = tmp_path / "poses.txt"
    t = torch.arange(3, dtype=torch.int64) * 1000
    poses = torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    writer(path, t, poses)
    before = path.read_bytes()
    with pytest.raises(ValueError):
        writer(path, t, poses[:2])  # one pose short: refused before anything is written
    with pytest.raises(ValueError, match="is a directory"):
        writer(tmp_path, t, poses)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.txt"]


def test_a_failing_frame_keeps_the_old_video(tmp_path):
    from torchevtrack.viz import save_video

    path = tmp_path / "overlay.gif"
    frame = np.zeros((8, 8, 3), dtype=np.uint8)
    save_video([frame, frame + 50], path, fps=5)
    before = path.read_bytes()

    def frames():
        yield frame
        raise RuntimeError("the renderer failed")

    with pytest.raises(RuntimeError):
        save_video(frames(), path, fps=5)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["overlay.gif"]


def test_a_live_pose_file_grows_as_one_file_and_formats_each_pose_once(tmp_path, monkeypatch):
    """`live --out` saves a growing trajectory every few seconds: each save rewrites the file atomically (the file
    equals write_tum's of every pose so far) and formats only the poses added since the last one."""
    import torchevtrack.io.poses as poses_io
    from torchevtrack.cli.live import PoseFile

    n, rng = 30, np.random.default_rng(1)
    t = torch.arange(1, n + 1, dtype=torch.int64) * 2000
    q = torch.nn.functional.normalize(torch.from_numpy(rng.normal(size=(n, 4))), dim=1)
    p = torch.cat([torch.from_numpy(rng.normal(size=(n, 3))), q], 1)
    formatted = []
    real = poses_io.tum_lines
    monkeypatch.setattr(poses_io, "tum_lines", lambda tt, pp: formatted.append(len(tt)) or real(tt, pp))
    out, ref = PoseFile(tmp_path / "sub" / "live.txt"), tmp_path / "ref.txt"
    for a, b in ((0, 12), (12, 13), (13, 30)):
        out.save(t[a:b], p[a:b])
        write_tum(ref, t[:b], p[:b])
        assert out.poses == b and out.path.read_bytes() == ref.read_bytes()
    assert formatted[0::2] == [12, 1, 17] and formatted[1::2] == [12, 13, 30]  # each save, then the reference
    assert not [f for f in out.path.parent.iterdir() if f.name != "live.txt"]  # no temporary file left
