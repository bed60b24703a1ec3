"""Event file formats: every reader on files written independently (h5py, numpy, struct, zstandard,
dv-processing, a hand-made EVT3 encoder), writer round trips, chunking, bad input, and the CLI."""

import struct
import sys
import zipfile

import h5py
import numpy as np
import pytest
import torch
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from torchevtrack.cli import main
from torchevtrack.events import EventStream
from torchevtrack.io.formats import (
    EventFileError,
    detect_format,
    iter_events,
    open_events,
    read_events,
    write_events,
)

def _arrays(n=500, seed=0, w=64, h=48, t0=0, span=10**6):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + span, n))
    t[5:8] = t[5]  # duplicate timestamps are kept
    return rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n)


def _check(ev: EventStream, x, y, t, p):
    assert ev.t.dtype == torch.int64 and ev.x.dtype == torch.int16 and ev.p.dtype == torch.int8
    for name, want in zip("xytp", (x, y, t, p)):
        np.testing.assert_array_equal(getattr(ev, name).numpy(), np.asarray(want, dtype=np.int64), err_msg=name)


# ---------------------------------------------------------------- files written independently

def _dsec(path, x, y, t, p, t_offset):
    with h5py.File(path, "w") as f:
        f["events/x"] = x.astype(np.uint16)
        f["events/y"] = y.astype(np.uint16)
        f["events/t"] = (t - t_offset).astype(np.uint32)
        f["events/p"] = p.astype(np.uint8)
        f["ms_to_idx"] = np.searchsorted(t - t_offset, np.arange(0, 1001) * 1000).astype(np.uint64)
        f["t_offset"] = np.int64(t_offset)


def _yarp_words(x, y, t_us, p, wrap_bits=31):
    """(ts, ae) word pairs, one event at a time, as ev::AE: p bit 0, x bits 1-10, y bits 12-20.

    Times are 80 ns ticks; even microseconds give whole ticks (12.5 ticks per us). The counter
    keeps the low ``wrap_bits`` bits (it wraps)."""
    out = []
    for xi, yi, ti, pi in zip(x, y, t_us, p):
        ticks = int(ti) * 25 // 2
        out.append((ticks % (1 << wrap_bits), int(pi) | int(xi) << 1 | int(yi) << 12))
    return out


def _evt3_bytes(x, y, t, p, width=64, height=48, vector=None):
    """EVT 3.0 from the Prophesee spec: TIME_HIGH (0x8, emitted for every 4096 us step, as sensors do,
    so the 24-bit time loop is visible) / TIME_LOW (0x6) / ADDR_Y (0x0) / ADDR_X (0x2)."""
    words, high = [], None
    for xi, yi, ti, pi in zip(x, y, t, p):
        ti = int(ti)
        start = ti >> 12 if high is None else high + 1
        for h in range(start, (ti >> 12) + 1):
            words.append(0x8000 | (h & 0xFFF))
        high = ti >> 12
        words += [0x6000 | (ti & 0xFFF), 0x0000 | int(yi), 0x2000 | int(pi) << 11 | int(xi)]
        if vector is not None and len(words) == 4:
            words += vector
    header = f"% evt 3.0\n% format EVT3;height={height};width={width}\n% end\n".encode()
    return header + struct.pack(f"<{len(words)}H", *words)


def _ycbev_bytes(x, y, t, p, frames=2):
    raw = b"".join(struct.pack("<ii", int(ti), int(xi) | int(yi) << 14 | int(pi) << 28)
                   for xi, yi, ti, pi in zip(x, y, t, p))
    cut = len(raw) // 16 * 8  # split into two zstd frames at an event boundary
    c = zstandard.ZstdCompressor()
    return c.compress(raw[:cut]) + c.compress(raw[cut:]) if frames == 2 else c.compress(raw)


def _write_independent(kind, d, arrays):
    x, y, t, p = arrays
    if kind == "dsec":
        path = d / "events.h5"
        _dsec(path, x, y, t, p, t_offset=int(t[0]) - 17)
    elif kind == "text":
        path = d / "events.csv"  # seconds, commas, columns x y t p, comments
        rows = np.stack([x, y, t // 10**6, t % 10**6, p], axis=1)
        np.savetxt(path, rows, fmt="%d,%d,%d.%06d,%d", header="x,y,t[s],p")
    elif kind == "yarp":
        path = d / "binaryevents.log"
        words = _yarp_words(x, y, t, p)
        words.insert(10, (words[10][0], 1 << 23 | 5 << 16 | 1234))  # IMU sample: skipped
        path.write_bytes(b"".join(struct.pack("<II", *w) for w in words))
    elif kind == "yarp_text":
        path = d / "data.log"
        words = _yarp_words(x, y, t, p)
        lines = [f"{k} {1700000000 + k * 0.004:.6f} AE ({' '.join(f'{a} {b}' for a, b in words[i:i + 37])})"
                 for k, i in enumerate(range(0, len(words), 37))]
        lines.insert(2, "2 1700000000.010000 IMUS (1 2 3 4)")
        path.write_text("\n".join(lines) + "\n")
    elif kind == "ycbev":
        path = d / "events.bin.zst"
        path.write_bytes(_ycbev_bytes(x, y, t, p))
    elif kind == "evt3":
        path = d / "rec.raw"
        path.write_bytes(_evt3_bytes(x, y, t, p))
    elif kind == "aedat4":
        dv = pytest.importorskip("dv_processing", reason="dv-processing writes the AEDAT4 test file")
        path = d / "rec.aedat4"
        writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.EventOnlyConfig("test", (64, 48)))
        for i in range(0, len(t), 97):  # several packets
            store = dv.EventStore()
            for xi, yi, ti, pi in zip(x[i:i + 97], y[i:i + 97], t[i:i + 97], p[i:i + 97]):
                store.push_back(int(ti), int(xi), int(yi), bool(pi))
            writer.writeEvents(store)
        del writer
    return path


FOREIGN = ["dsec", "text", "yarp", "yarp_text", "ycbev", "evt3", "aedat4"]
_OPTS = {"text": {"columns": "xytp"}}


def _foreign_arrays(kind):
    if kind in ("yarp", "yarp_text"):
        x, y, t, p = _arrays(n=400, seed=1)
        return x, y, t // 2 * 2, p  # even microseconds: exact 80 ns ticks
    if kind == "aedat4":
        return _arrays(n=400, seed=2, t0=1_700_000_000_000_000)  # absolute Unix microseconds
    return _arrays(n=400, seed=3, t0=123_456)


@pytest.mark.parametrize("kind", FOREIGN)
def test_reader_on_independent_file(tmp_path, kind):
    arrays = _foreign_arrays(kind)
    path = _write_independent(kind, tmp_path, arrays)
    assert detect_format(path) == kind
    ev = read_events(path, **_OPTS.get(kind, {}))
    _check(ev, *arrays)
    # chunk sizes that split the file (and packets, bottles, zstd frames) oddly
    for chunk in (1, 3, 37, 399, 400, 1000):
        parts = list(iter_events(path, chunk_events=chunk, **_OPTS.get(kind, {})))
        assert all(len(c) == chunk for c in parts[:-1]) and 0 < len(parts[-1]) <= chunk
        _check(EventStream.concat(parts), *arrays)


def test_evt3_sensor_size_vector_words_and_time_high_loop(tmp_path):
    # after the first event, a vectorised group on row 7 (VECT_BASE_X at x=10 + VECT_12 mask
    # 0b101000000001: x = 10, 19, 21); the last event lies past the 24-bit time loop (16.8 s)
    t1 = (1 << 12) + 5
    vector = [0x3000 | 1 << 11 | 10, 0x4000 | 0b101000000001]
    path = tmp_path / "v.raw"
    path.write_bytes(_evt3_bytes([4, 2], [7, 3], [t1, 20_000_000], [0, 0], width=30, height=20, vector=vector))
    ef = open_events(path)
    assert (ef.width, ef.height) == (30, 20)
    _check(read_events(path), [4, 10, 19, 21, 2], [7, 7, 7, 7, 3], [t1, t1, t1, t1, 20_000_000], [0, 1, 1, 1, 0])


def test_yarp_timestamp_wrap_channel_and_clock(tmp_path):
    x, y, t, p = np.array([1, 2, 3, 4]), np.array([5, 6, 7, 8]), np.array([0, 171_798_600, 171_798_692, 171_800_000]), \
        np.array([1, 0, 1, 0])  # 2**31 ticks of 80 ns = 171.798...s: the counter wraps between events 1 and 2
    words = _yarp_words(x, y, t, p)
    assert words[2][0] < words[1][0]
    words[1] = (words[1][0], words[1][1] | 1 << 22)  # right channel
    path = tmp_path / "binaryevents.log"
    path.write_bytes(b"".join(struct.pack("<II", *w) for w in words))
    _check(read_events(path), x, y, t, p)
    _check(read_events(path, channel=0), x[[0, 2, 3]], y[[0, 2, 3]], t[[0, 2, 3]], p[[0, 2, 3]])
    _check(read_events(path, invert_polarity=True), x, y, t, 1 - p)
    # a 1 us clock (USB ATIS builds): the same words mean 12.5x longer times, rounded to microseconds
    ticks = np.array([w[0] for w in words], dtype=np.int64) + np.array([0, 0, 1, 1]) * 2**31
    _check(read_events(path, clock_period_ns=1000), x, y, ticks, p)


# ---------------------------------------------------------------- writers

WRITERS = [("a.h5", {}), ("a.npz", {}), ("a.npz", {"compress": True}), ("a.txt", {}),
           ("a.txt", {"time_unit": "s"}), ("a.csv", {})]


@pytest.mark.parametrize("name,opts", WRITERS)
def test_writer_round_trip_streamed(tmp_path, name, opts):
    arrays = _arrays(n=300, seed=4, t0=10**12)
    ev = EventStream.from_arrays(*arrays)
    path = tmp_path / name
    n = write_events(path, (ev[i:i + 41] for i in range(0, len(ev), 41)), width=64, height=48, **opts)
    assert n == len(ev)
    _check(read_events(path), *arrays)
    for chunk in (1, 7, 299, 301):
        _check(EventStream.concat(list(iter_events(path, chunk_events=chunk))), *arrays)
    if not name.endswith((".txt", ".csv")):
        ef = open_events(path)
        assert (ef.width, ef.height) == (64, 48)


def test_writer_rejects_bad_streams(tmp_path):
    ev = EventStream.from_arrays(*_arrays(n=50, seed=5))
    with pytest.raises(ValueError, match="precedes"):
        write_events(tmp_path / "a.npz", [ev[25:], ev[:25]])
    assert not (tmp_path / "a.npz").exists()  # nothing written after a failure
    with pytest.raises(ValueError, match="out of bounds"):
        write_events(tmp_path / "a.txt", ev, width=10, height=48)
    with pytest.raises(ValueError, match="cannot be written"):
        write_events(tmp_path / "a.raw", ev, format="evt3")
    with pytest.raises(ValueError, match="output format"):
        write_events(tmp_path / "a.bin", ev)


# ---------------------------------------------------------------- validation and repair

def _npz(path, x, y, t, p):
    np.savez(path, x=np.asarray(x), y=np.asarray(y), t=np.asarray(t, dtype=np.int64), p=np.asarray(p))


def test_unsorted_time_error_names_index_and_sort_repairs(tmp_path):
    x, y, t, p = _arrays(n=100, seed=6)
    t = t.copy()
    t[[40, 41]] = t[[41, 40]] if t[40] != t[41] else (t[40] + 1, t[40])
    _npz(tmp_path / "a.npz", x, y, t, p)
    for chunk in (1000, 41, 40, 7):  # inside a chunk and across a chunk boundary
        with pytest.raises(EventFileError, match="not sorted: event 41 "):
            read_events(tmp_path / "a.npz", chunk_events=chunk)
    ev = read_events(tmp_path / "a.npz", sort=True, chunk_events=9)
    order = np.argsort(t, kind="stable")
    _check(ev, x[order], y[order], t[order], p[order])


def test_out_of_bounds_error_and_drop(tmp_path):
    x, y, t, p = _arrays(n=100, seed=7, w=80)
    _npz(tmp_path / "a.npz", x, y, t, p)
    first = int(np.argmax(x >= 64))
    with pytest.raises(EventFileError, match=f"event {first} has x={x[first]}, sensor x-size is 64"):
        read_events(tmp_path / "a.npz", width=64, height=48)
    keep = x < 64
    ev = read_events(tmp_path / "a.npz", width=64, height=48, drop_out_of_bounds=True, chunk_events=13)
    _check(ev, x[keep], y[keep], t[keep], p[keep])
    _npz(tmp_path / "b.npz", np.r_[x[:3], -1], y[:4], t[:4], p[:4])
    with pytest.raises(EventFileError, match="event 3 has x=-1"):
        read_events(tmp_path / "b.npz")


def test_time_and_polarity_checks(tmp_path):
    _npz(tmp_path / "neg.npz", [0, 1], [0, 0], [-5, 3], [0, 1])
    with pytest.raises(EventFileError, match="negative timestamp -5 us at event 0"):
        read_events(tmp_path / "neg.npz")
    np.savez(tmp_path / "big.npz", x=np.zeros(2, int), y=np.zeros(2, int), p=np.zeros(2, int),
             t=np.array([1, 2**63 + 5], dtype=np.uint64))
    with pytest.raises(EventFileError, match="event 1 overflows int64"):
        read_events(tmp_path / "big.npz")
    _npz(tmp_path / "pol.npz", [0, 1, 2], [0, 0, 0], [1, 2, 3], [1, 2, 0])
    with pytest.raises(EventFileError, match="polarity 2 at event 1"):
        read_events(tmp_path / "pol.npz")
    for pol in ([-1, 1, -1], [False, True, False]):
        _npz(tmp_path / "ok.npz", [0, 1, 2], [0, 0, 0], [1, 2, 3], pol)
        _check(read_events(tmp_path / "ok.npz"), [0, 1, 2], [0, 0, 0], [1, 2, 3], [0, 1, 0])


def test_text_options_and_errors(tmp_path):
    path = tmp_path / "e.txt"
    path.write_text("# comment with a dot.\n10 1 2 1\n\n20 3 4 0  # trailing\n30 5 6 -1\n")
    _check(read_events(path), [1, 3, 5], [2, 4, 6], [10, 20, 30], [1, 0, 0])
    _check(read_events(path, time_unit="s"), [1, 3, 5], [2, 4, 6], [10**7, 2 * 10**7, 3 * 10**7], [1, 0, 0])
    path.write_text("10 1 2 1\n20 3 4 0\n30.5 5 6 1\n")
    with pytest.raises(EventFileError, match="line 3: .*time_unit='s'"):
        read_events(path, chunk_events=2)  # first block decides integer microseconds
    path.write_text("0.5 1 2 1\n0.25 3 4\n")
    with pytest.raises(EventFileError, match=r"byte offset 10\): line 2: expected 4 values"):
        read_events(path)
    path.write_text("0.5 1.5 2 1\n")
    with pytest.raises(EventFileError, match="line 1: x is not an integer"):
        read_events(path)
    path.write_bytes(b"1 2 3 4\n\xff\xfe\n")
    with pytest.raises(EventFileError, match="byte offset 8.*UTF-8"):
        read_events(path, format="text")
    with pytest.raises(ValueError, match="columns"):
        read_events(path, format="text", columns="txy")


# ---------------------------------------------------------------- broken files

def test_truncated_and_corrupt_files(tmp_path):
    x, y, t, p = _arrays(n=200, seed=8)
    # YARP: a partial 8-byte event at the end
    words = _yarp_words(x, y, t // 2 * 2, p)
    data = b"".join(struct.pack("<II", *w) for w in words)
    (tmp_path / "binaryevents.log").write_bytes(data[:-3])
    with pytest.raises(EventFileError, match=r"byte offset 1592\): truncated"):
        open_events(tmp_path / "binaryevents.log")
    # YCB-Ev: cut inside the last frame, corrupted payload, wrong magic, stray high bits
    z = _ycbev_bytes(x, y, t, p, frames=1)
    (tmp_path / "cut.zst").write_bytes(z[:-7])
    with pytest.raises(EventFileError, match="truncated zstd stream"):
        read_events(tmp_path / "cut.zst")
    (tmp_path / "bad.zst").write_bytes(z[:12] + bytes(b ^ 0x5A for b in z[12:60]) + z[60:])
    with pytest.raises(EventFileError, match="corrupt zstd data"):
        read_events(tmp_path / "bad.zst")
    (tmp_path / "magic.zst").write_bytes(b"\x00" + z[1:])
    with pytest.raises(EventFileError, match=r"byte offset 0\): not a zstd stream"):
        read_events(tmp_path / "magic.zst", format="ycbev")
    (tmp_path / "bits.zst").write_bytes(zstandard.ZstdCompressor().compress(struct.pack("<iIiI", 1, 3, 2, 1 << 30)))
    with pytest.raises(EventFileError, match="event 1: address word 0x40000000"):
        read_events(tmp_path / "bits.zst")
    # npz cut short, or with a member's bytes flipped (CRC)
    _npz(tmp_path / "a.npz", x, y, t, p)
    blob = (tmp_path / "a.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(EventFileError, match="npz"):
        read_events(tmp_path / "cut.npz", format="npz")
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        start = zf.getinfo("t.npy").header_offset + 200
    (tmp_path / "crc.npz").write_bytes(blob[:start] + bytes([blob[start] ^ 1]) + blob[start + 1:])
    with pytest.raises(EventFileError, match="Bad CRC-32"):
        read_events(tmp_path / "crc.npz")
    # EVT3: unsupported version header, no header, data cut mid-word
    (tmp_path / "v2.raw").write_bytes(b"% evt 2.0\n% end\n" + b"\x00" * 16)
    with pytest.raises(EventFileError, match=r"byte offset 0\): unsupported raw encoding \(EVT 2.0\)"):
        read_events(tmp_path / "v2.raw")
    (tmp_path / "nohdr.raw").write_bytes(b"\x01\x02" * 8)
    with pytest.raises(EventFileError, match="no '%' header"):
        read_events(tmp_path / "nohdr.raw", format="evt3")
    (tmp_path / "cut.raw").write_bytes(_evt3_bytes(x, y, t, p)[:-1])
    with pytest.raises(EventFileError, match="EVT3 decoding failed"):
        read_events(tmp_path / "cut.raw")
    # AEDAT: other versions and wrong magic
    (tmp_path / "old.aedat").write_bytes(b"#!AER-DAT3.1\r\n" + b"\x00" * 64)
    with pytest.raises(EventFileError, match="AEDAT version 3.1 is not supported"):
        read_events(tmp_path / "old.aedat")
    (tmp_path / "x.aedat4").write_bytes(b"#!AER-DAT2.0\r\n")
    with pytest.raises(EventFileError, match=r"byte offset 0\): not an AEDAT 4 file"):
        read_events(tmp_path / "x.aedat4", format="aedat4")
    # YARP text: a malformed bottle line
    (tmp_path / "data.log").write_text("0 1.0 AE (1 2 3 4)\n1 1.1 AE (1 2 3\n")
    with pytest.raises(EventFileError, match=r"byte offset 19\): line 2: not a YARP bottle"):
        read_events(tmp_path / "data.log")
    # something unrecognisable, and DSEC-like HDF5 without events
    (tmp_path / "junk.bin").write_bytes(b"\x00\x01garbage" * 10)
    with pytest.raises(EventFileError, match="unrecognised event file"):
        read_events(tmp_path / "junk.bin")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["images"] = np.zeros(3)
    with pytest.raises(EventFileError, match="neither our layout"):
        read_events(tmp_path / "other.h5")


def test_missing_optional_dependency_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "e.zst"
    path.write_bytes(_ycbev_bytes(*_arrays(n=10), frames=1))
    monkeypatch.setitem(sys.modules, "zstandard", None)  # import now raises ImportError
    with pytest.raises(ImportError, match=r'pip install "torchevtrack\[io\]"'):
        read_events(path)


# ---------------------------------------------------------------- property-based round trips

_events = st.integers(0, 60).flatmap(lambda n: st.tuples(
    st.lists(st.integers(0, 2000), min_size=n, max_size=n),
    st.lists(st.integers(0, 1000), min_size=n, max_size=n),
    st.lists(st.integers(0, 2**40), min_size=n, max_size=n),
    st.lists(st.sampled_from([-1, 0, 1]), min_size=n, max_size=n)))


@settings(max_examples=25, deadline=None)
@given(ev=_events, chunk=st.integers(1, 70), fmt=st.sampled_from(["h5", "npz", "txt-us", "txt-s"]))
def test_property_write_read_equal(tmp_path_factory, ev, chunk, fmt):
    x, y, t, p = (np.asarray(a, dtype=np.int64) for a in ev)
    t = np.sort(t)
    stream = EventStream.from_arrays(x, y, t, p)
    path = tmp_path_factory.mktemp("prop") / ("e." + fmt.split("-")[0])
    opts = {"time_unit": fmt.split("-")[1]} if fmt.startswith("txt") else {}
    write_events(path, stream, **opts)
    got = EventStream.concat(list(iter_events(path, chunk_events=chunk, **opts)))
    _check(got, x, y, t, (p > 0).astype(np.int64))


# ---------------------------------------------------------------- CLI

def test_cli_convert(tmp_path, capsys):
    arrays = _foreign_arrays("yarp")
    src = _write_independent("yarp", tmp_path, arrays)
    out = tmp_path / "out.h5"
    assert main(["convert", str(src), str(out), "--chunk", "33", "--width", "64", "--height", "48"]) == 0
    assert "wrote 400 events" in capsys.readouterr().out
    _check(read_events(out), *arrays)
    assert (open_events(out).width, open_events(out).height) == (64, 48)
    assert main(["convert", str(out), str(tmp_path / "o.txt"), "--quiet", "--width", "30", "--height", "48",
                 "--drop-out-of-bounds"]) == 0
    keep = arrays[0] < 30
    _check(read_events(tmp_path / "o.txt"), *(a[keep] for a in arrays))
    assert main(["convert", str(out), str(tmp_path / "o.npz"), "--width", "30", "--height", "48"]) == 2
    assert "sensor x-size is 30" in capsys.readouterr().err


def test_cli_info_on_event_file(tmp_path, capsys):
    import json

    x, y, t, p = _foreign_arrays("ycbev")
    path = _write_independent("ycbev", tmp_path, (x, y, t, p))
    assert main(["info", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["format"] == "ycbev" and s["events"] == len(t)
    assert (s["t_first_us"], s["t_last_us"]) == (int(t[0]), int(t[-1]))
    assert s["x_range"] == [int(x.min()), int(x.max())] and s["y_range"] == [int(y.min()), int(y.max())]
    assert s["on_fraction"] == pytest.approx(p.mean())
    assert main(["info", str(path)]) == 0
    assert f"events     {len(t)} over" in capsys.readouterr().out
