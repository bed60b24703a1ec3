"""Executors: the same results serially, on a local process pool and on a local Ray (2 CPUs)."""

import json
import math
import time

import numpy as np
import pytest

from torchevtrack.benchmark import run_benchmark
from torchevtrack.camera import Camera
from torchevtrack.executor import make_executor
from torchevtrack.io.poses import read_tum
from torchevtrack.synth.generate import generate_sequence

CAM = Camera(160, 120, 125.6, 125.6, 79.5, 59.5)
SEQS = {"cracker_regular": ("box", "regular", 1), "tomato_fast": ("can", "fast", 2)}


def _fails(x):
    if x == 2:
        raise RuntimeError("task 2 failed")
    return x


def test_map_keeps_the_task_order_and_raises_the_first_failure():
    with make_executor("serial") as ex:
        assert ex.map(math.factorial, [5, 0, 3], progress=False) == [120, 1, 6]
        with pytest.raises(RuntimeError, match="task 2"):
            ex.map(_fails, [1, 2, 3], progress=False)
    with make_executor("process", workers=2) as ex:
        assert ex.map(math.factorial, list(range(12, 0, -1)), progress=False) == \
            [math.factorial(k) for k in range(12, 0, -1)]
        with pytest.raises(RuntimeError, match="task 2"):
            ex.map(_fails, [1, 2, 3], progress=False)


@pytest.mark.parametrize("kind, kw, message", [
    ("dask", {}, "executor must be one of serial, process, ray"),
    ("process", {"address": "auto"}, "--address is for --executor ray"),
    ("serial", {"workers": 2}, "--jobs is for"),
    ("process", {"workers": 0}, "workers must be a positive integer"),
])
def test_bad_executor_arguments(kind, kw, message):
    with pytest.raises(ValueError, match=message):
        make_executor(kind, **kw)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    for name, (obj, motion, seed) in SEQS.items():
        generate_sequence(obj, motion, 0.03, seed=seed, camera=CAM, progress=False).save(root / name)
    return root


def _strip(res: dict) -> dict:
    """results.json without what depends on when and where it ran (timing, date, machine)."""
    res = json.loads(json.dumps(res))
    for key in ("date", "machine", "runs", "executor"):
        res.pop(key)
    for per_seq in res["results"].values():
        for r in per_seq.values():
            r.pop("timing")
    return res


def test_ray_and_process_pool_results_equal_the_serial_ones(bench, tmp_path, capsys):
    pytest.importorskip("ray", reason="the ray extra is not installed")
    from torchevtrack.cli import main

    kw = dict(methods=("full", "velocity_only"), batch=False, overlays=False, progress=False)
    start = time.perf_counter()
    serial = run_benchmark(bench, tmp_path / "serial", **kw)
    wall = {"serial": time.perf_counter() - start}
    for kind in ("process", "ray"):
        start = time.perf_counter()
        assert main(["benchmark", str(bench), "--out", str(tmp_path / kind), "--methods", "full,velocity_only",
                     "--no-overlays", "--quiet", "--executor", kind, "--jobs", "2"]) == 0
        wall[kind] = time.perf_counter() - start
        other = json.loads((tmp_path / kind / "results.json").read_text())
        assert other["executor"] == kind and serial["executor"] == "serial"
        assert len(other["runs"]["full"]) == 2  # one task per (sequence, method): no batches with a parallel executor
        assert _strip(other) == _strip(serial), kind
        for m in kw["methods"]:
            for name in SEQS:
                a, b = read_tum(tmp_path / "serial" / "poses" / m / f"{name}.txt"), \
                    read_tum(tmp_path / kind / "poses" / m / f"{name}.txt")
                assert np.array_equal(a[1].numpy(), b[1].numpy()) and np.array_equal(a[0].numpy(), b[0].numpy())
    capsys.readouterr()
    print("wall s:", {k: round(v, 1) for k, v in wall.items()})  # shown with -s


def test_synth_benchmark_on_ray_writes_the_serial_sequences(tmp_path, capsys):
    pytest.importorskip("ray", reason="the ray extra is not installed")
    from torchevtrack.cli import main
    from torchevtrack.synth.sequence import Sequence

    names = ["potted_regular", "tomato_fast"]
    for kind, extra in (("serial", []), ("ray", ["--jobs", "2"])):
        assert main(["synth-benchmark", "--out", str(tmp_path / kind), "--duration", "0.01", "--only", *names,
                     "--quiet", "--executor", kind, *extra]) == 0
    printed = capsys.readouterr().out
    assert printed.count("potted_regular: ") == 2 and printed.count("tomato_fast: ") == 2  # each as it completes
    for name in names:
        a, b = Sequence.load(tmp_path / "serial" / name), Sequence.load(tmp_path / "ray" / name)
        assert len(a.events) > 0
        for f in "xytp":
            assert np.array_equal(getattr(a.events, f).numpy(), getattr(b.events, f).numpy()), (name, f)
        assert np.array_equal(a.gt_poses.numpy(), b.gt_poses.numpy()) and a.meta == b.meta
    assert (tmp_path / "ray" / "suite.json").read_text() == (tmp_path / "serial" / "suite.json").read_text()
