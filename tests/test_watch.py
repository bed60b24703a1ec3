"""rerun logging: ``track --rerun FILE.rrd`` and the RerunLogger hook write a recording that loads back with the
rerun SDK and holds the documented entities, with the tracked poses and errors of the run."""

import numpy as np
import pytest
import torch

rr = pytest.importorskip("rerun", reason="the rerun extra is not installed")
from rerun.chunk import RrdReader  # noqa: E402

from torchevtrack.camera import Camera  # noqa: E402
from torchevtrack.cli import main  # noqa: E402
from torchevtrack.geometry import interpolate_poses  # noqa: E402
from torchevtrack.io.poses import read_tum  # noqa: E402
from torchevtrack.metrics import pose_errors  # noqa: E402
from torchevtrack.online import OnlineTracker  # noqa: E402
from torchevtrack.synth.generate import generate_sequence  # noqa: E402
from torchevtrack.synth.sequence import Sequence  # noqa: E402
from torchevtrack.tracker import EventPoseTracker  # noqa: E402
from torchevtrack.watch import RerunLogger, silhouette_segments  # noqa: E402

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)


@pytest.fixture(scope="module")
def seqdir(tmp_path_factory):
    root = tmp_path_factory.mktemp("watch")
    generate_sequence("box", "regular", 0.04, seed=4, camera=CAM, progress=False).save(root / "seq")
    return root / "seq"


def _rows(path) -> dict[str, list]:
    """Per entity path, the record batches of its temporal chunks (sorted by the update timeline)."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        if not chunk.is_static:
            out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches, suffix: str) -> np.ndarray:
    """The values of the column whose name ends with ``suffix``, in update order."""
    pairs = []
    for rb in batches:
        names = rb.schema.names
        upd = rb.column(names.index("update")).to_pylist()
        col = rb.column(next(i for i, n in enumerate(names) if n.endswith(suffix))).to_pylist()
        pairs += [(u, v) for u, v in zip(upd, col) if v is not None]
    return np.array([np.asarray(v, dtype=np.float64).reshape(-1) for _, v in sorted(pairs, key=lambda p: p[0])])


def test_track_rerun_writes_every_entity(seqdir, tmp_path, capsys):
    rrd, out = tmp_path / "run.rrd", tmp_path / "poses.txt"
    assert main(["track", str(seqdir), "--out", str(out), "--rerun", str(rrd), "--set", "loss.enabled=true",
                 "--quiet"]) == 0
    assert f"rerun recording: {rrd}" in capsys.readouterr().out
    schema = RrdReader(rrd).stream().collect().schema()
    paths = set(schema.entity_paths())
    expected = {"/world/camera", "/world/camera/eros", "/world/camera/eros/tracked", "/world/camera/eros/truth",
                "/world/object", "/world/object/mesh", "/world/trajectory/tracked", "/world/trajectory/truth",
                "/errors/translation_cm", "/errors/rotation_deg", "/quality/score", "/quality/rejected",
                "/loss/lost", "/timing/correction_ms", "/timing/ukf_ms", "/timing/flow_ms", "/timing/render_ms"}
    assert expected <= paths, expected - paths

    # the logged poses and errors are those of the pose file and of the metrics against the ground truth
    t_us, poses = read_tum(out)
    rows = _rows(rrd)
    translation = _column(rows["/world/object"], "translation")
    assert translation.shape == (len(t_us), 3)
    np.testing.assert_allclose(translation, poses[:, :3].numpy(), atol=1e-6)
    seq = Sequence.load(seqdir)
    e = pose_errors(poses, interpolate_poses(seq.gt_t_us, seq.gt_poses, t_us))
    np.testing.assert_allclose(_column(rows["/errors/translation_cm"], "scalars")[:, 0], e["te"].numpy() * 100,
                               atol=1e-6)  # the pose file's rounding: < 1e-8 m
    np.testing.assert_allclose(_column(rows["/errors/rotation_deg"], "scalars")[:, 0], np.degrees(e["re"].numpy()),
                               atol=1e-5)
    lost = _column(rows["/loss/lost"], "scalars")
    assert lost.shape == (len(t_us), 1) and set(lost[:, 0].tolist()) <= {0.0, 1.0}
    # images every 20 ms of the sequence: the first update, then one per 20 ms
    assert len(_column(rows["/world/camera/eros"], "buffer")) == 1 + (int(t_us[-1] - t_us[0]) // 20_000)


def test_the_logger_hook_fires_for_the_online_tracker(seqdir, tmp_path):
    seq = Sequence.load(seqdir)
    tracker = EventPoseTracker(seq.camera, seqdir / "mesh.ply")
    rrd = tmp_path / "online.rrd"
    logger = RerunLogger(seq.camera, seqdir / "mesh.ply", path=rrd, image_period_us=0).attach(tracker)
    online = OnlineTracker(tracker)
    online.start(seq.gt_poses[0], int(seq.gt_t_us[0]))
    out = online.push(seq.events) + online.flush(int(seq.gt_t_us[-1]))
    logger.close()
    tracker.close()
    rows = _rows(rrd)
    translation = _column(rows["/world/object"], "translation")
    np.testing.assert_allclose(translation, torch.stack([p[0, :3] for _, p in out]).numpy(), atol=1e-6)
    assert len(_column(rows["/world/camera/eros"], "buffer")) == len(out)  # image_period_us=0: every update
    assert "/errors/translation_cm" not in rows  # no ground truth given


def test_silhouette_of_a_box_facing_the_camera_is_its_outline():
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    pose = torch.tensor([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    seg = silhouette_segments(box, pose, CAM)
    # the front face's outline: its 4 edges (each face split in two triangles; the diagonals are not silhouette)
    u = CAM.fx * 0.05 / 0.45
    corners = {(round(CAM.cx + sx * u, 3), round(CAM.cy + sy * u, 3)) for sx in (-1, 1) for sy in (-1, 1)}
    ends = {(round(float(a), 3), round(float(b), 3)) for a, b in seg.reshape(-1, 2)}
    assert len(seg) == 4 and ends == corners
