import h5py
import numpy as np
import pytest
import torch
import trimesh

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.io.events_h5 import events_h5_summary, iter_events_h5, read_events_h5, write_events_h5
from torchevtrack.synth.sequence import Sequence

CAM = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)


def random_events(n=5000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 50_000, n))
    return EventStream.from_arrays(x=rng.integers(0, 64, n), y=rng.integers(0, 48, n), t=t, p=rng.integers(0, 2, n))


def make_sequence():
    t_us = torch.arange(0, 50_001, 2000, dtype=torch.int64)
    q = torch.nn.functional.normalize(torch.randn(len(t_us), 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)), dim=-1)
    q = torch.where(q[:, :1] < 0, -q, q)
    xyz = torch.stack((0.01 * torch.sin(t_us / 1e4), torch.zeros(len(t_us)), 0.5 + 0.0 * t_us), -1).double()
    return Sequence(random_events(), CAM, t_us, torch.cat((xyz, q), -1), trimesh.creation.box((0.05, 0.06, 0.07)),
                    {"object": "box", "seed": 3})


def write_raw(path, **over):
    ev = random_events(100)
    data = {"x": ev.x.numpy(), "y": ev.y.numpy(), "t": ev.t.numpy(), "p": ev.p.numpy()}
    data.update(over)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            f.create_dataset(k, data=v)


def test_roundtrip(tmp_path):
    seq = make_sequence()
    seq.save(tmp_path / "s")
    back = Sequence.load(tmp_path / "s")
    for f in ("x", "y", "t", "p"):
        a, b = getattr(seq.events, f), getattr(back.events, f)
        assert a.dtype == b.dtype and torch.equal(a, b)
    assert back.camera == CAM and torch.equal(back.gt_t_us, seq.gt_t_us)
    assert torch.allclose(back.gt_poses, seq.gt_poses, atol=1e-8)
    assert np.allclose(back.mesh.vertices, seq.mesh.vertices) and back.meta == seq.meta
    with h5py.File(tmp_path / "s" / "events.h5") as f:
        assert f["t"].dtype == np.int64 and f["x"].dtype == np.int16 and f["t"].compression == "gzip"


def test_a_textured_model_round_trips_beside_the_mesh(tmp_path):
    from torchevtrack.raster import raster_arrays
    from torchevtrack.synth.sequence import TEXTURED_MESH
    from torchevtrack.synth.texture import printed_texture

    seq = make_sequence()
    seq.save(tmp_path / "plain")
    assert not (tmp_path / "plain" / TEXTURED_MESH).exists() and Sequence.load(tmp_path / "plain").textured_mesh is None
    seq.textured_mesh = printed_texture(seq.mesh, seed=5, size=64)
    back = Sequence.load(seq.save(tmp_path / "printed"))
    assert back.mesh.visual.kind is None  # mesh.ply stays the geometry
    a, tex = raster_arrays(back.textured_mesh)
    a0, tex0 = raster_arrays(seq.textured_mesh)  # the rasteriser reads the same triangles, UVs and texels
    assert tex is not None and np.array_equal(tex.texels, tex0.texels) and np.array_equal(tex.levels, tex0.levels)
    assert np.allclose(a.vertices, a0.vertices) and np.array_equal(a.faces, a0.faces)
    assert np.allclose(tex.uv, tex0.uv, atol=1e-6)


def test_h5_bytes_deterministic(tmp_path):
    ev = random_events()
    write_events_h5(tmp_path / "a.h5", ev, width=64, height=48)
    write_events_h5(tmp_path / "b.h5", ev, width=64, height=48)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()


def test_chunked_reader_matches_full_read(tmp_path):
    ev = random_events(10_007)
    write_events_h5(tmp_path / "e.h5", ev)
    chunks = list(iter_events_h5(tmp_path / "e.h5", chunk=1000))
    assert [len(c) for c in chunks] == [1000] * 10 + [7]
    joined = EventStream.concat(chunks)
    assert torch.equal(joined.t, ev.t) and torch.equal(joined.x, ev.x) and torch.equal(joined.p, ev.p)
    s = events_h5_summary(tmp_path / "e.h5")
    assert (s["n"], s["t_first_us"], s["t_last_us"]) == (10_007, int(ev.t[0]), int(ev.t[-1]))


def test_missing_file_is_named(tmp_path):
    make_sequence().save(tmp_path / "s")
    (tmp_path / "s" / "gt_poses.txt").unlink()
    with pytest.raises(FileNotFoundError, match="gt_poses.txt"):
        Sequence.load(tmp_path / "s")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        Sequence.load(tmp_path / "nowhere")


def test_wrong_dtype(tmp_path):
    ev = random_events(100)
    write_raw(tmp_path / "f.h5", t=ev.t.numpy().astype(np.float64) / 1e6)
    with pytest.raises(ValueError, match="'t' has dtype float64, expected integers microseconds"):
        read_events_h5(tmp_path / "f.h5")


def test_stored_values_are_checked_before_narrowing(tmp_path):
    """An x of 40000 stored as int32 or a polarity of 257 is an error, not a wrapped pixel or polarity 1;
    int32 timestamps are read exactly (as int64)."""
    ev = random_events(100)
    x = ev.x.numpy().astype(np.int32)
    x[5] = 40000
    write_raw(tmp_path / "x.h5", x=x)
    with pytest.raises(ValueError, match=r"event 5 has x=40000, outside \[0, 32768\)"):
        read_events_h5(tmp_path / "x.h5")
    p = ev.p.numpy().astype(np.int16)
    p[9] = 257
    write_raw(tmp_path / "p.h5", p=p)
    with pytest.raises(ValueError, match=r"event 9 has p=257, a polarity not in \{0, 1\}"):
        read_events_h5(tmp_path / "p.h5")
    write_raw(tmp_path / "t32.h5", t=ev.t.numpy().astype(np.int32))
    got = read_events_h5(tmp_path / "t32.h5")
    assert got.t.dtype == torch.int64 and torch.equal(got.t, ev.t)


def test_unsorted_time_names_event(tmp_path):
    t = random_events(100).t.numpy().copy()
    t[37] = t[36] - 1
    write_raw(tmp_path / "u.h5", t=t)
    with pytest.raises(ValueError, match="event 37"):
        read_events_h5(tmp_path / "u.h5")
    # across a chunk boundary the global index is reported too
    with pytest.raises(ValueError, match="event 37"):
        list(iter_events_h5(tmp_path / "u.h5", chunk=37))


def test_out_of_bounds_names_event(tmp_path):
    seq = make_sequence()
    seq.save(tmp_path / "s")
    x = seq.events.x.numpy().copy()
    x[1234] = 64
    with h5py.File(tmp_path / "s" / "events.h5", "r+") as f:
        f["x"][:] = x
    with pytest.raises(ValueError, match="event 1234 has x=64"):
        Sequence.load(tmp_path / "s")
    write_raw(tmp_path / "n.h5", p=np.full(100, 2, dtype=np.int8))
    with pytest.raises(ValueError, match="polarity"):
        read_events_h5(tmp_path / "n.h5")
