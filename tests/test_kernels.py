"""The kernels' cache: a cold cache is detected (from an empty NUMBA_CACHE_DIR), announced once in one line, and
warm after a first run; `warmup` leaves no module of the tracker cold; a kernel called from Python and from
compiled steps compiles once."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run_cold(script: str, cache_dir: Path) -> subprocess.CompletedProcess:
    """``script`` in a fresh Python process whose numba cache is the empty ``cache_dir``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache_dir)}
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600,
                          check=True)


def test_a_cold_cache_is_announced_once_and_warm_after_first_use(tmp_path):
    script = (
        "import sys\n"
        "import torchevtrack.events\n"
        "from torchevtrack.kernels import announce_compile, uncached_kernels\n"
        "print(sorted(uncached_kernels()))\n"
        "announce_compile(); announce_compile()\n"
        "torchevtrack.events.EventStream.from_arrays([1], [2], [3], [1], width=4, height=4)\n"
        "print(sorted(uncached_kernels()))\n"
    )
    r = _run_cold(script, tmp_path)
    before, after = r.stdout.splitlines()
    assert before == "['torchevtrack.events._first_outside', 'torchevtrack.events.first_invalid']"
    assert after == "[]"
    notice = r.stderr.strip().splitlines()
    assert len(notice) == 1 and notice[0].startswith("torchevtrack: compiling 2 numba kernels on first use")
    assert "torchevtrack warmup" in notice[0]


def test_warmup_leaves_no_tracker_module_cold(capsys):
    import torchevtrack.online  # noqa: F401  (the modules a tracking run loads)
    import torchevtrack.tracker  # noqa: F401
    from torchevtrack.kernels import uncached_kernels, warmup

    warmup(progress=False)
    # torchevtrack.reference holds the tests' torch/numba oracles, which a tracking run never calls: earlier tests
    # in the same process may have loaded it without compiling all of it
    assert [n for n in uncached_kernels() if not n.startswith("torchevtrack.reference.")] == []
    assert "compiling" not in capsys.readouterr().err  # warmup reports through its own bar, not the notice


def test_propagate_and_twist_between_from_python_and_from_the_update_compile_once(tmp_path):
    # A second signature of a kernel is a second compilation on a cold start (10-15 s each). The update passes its
    # read-only periods (stages.periods) to propagate_kernel and twist_between_kernel from compiled steps; Python's
    # propagate and twist_between (metrics, recovery) must type their dt alike.
    script = (
        "import numpy as np, torch\n"
        "from torchevtrack.stages import periods\n"
        "from torchevtrack.stages.propagate import (propagate, propagate_kernel, propagate_step, twist_between,\n"
        "                                           twist_between_kernel)\n"
        "pose = np.tile([0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0], (2, 1)); twist = np.ones((2, 6))\n"
        "propagate_step(pose, twist, periods(2, 0.002), np.zeros(2), np.empty((2, 7)), np.empty(2, np.bool_))\n"
        "twist_between_kernel(pose, pose, periods(2, 0.002), np.empty((2, 6)))\n"
        "for dt in (0.002, torch.full((2,), 0.002, dtype=torch.float64)):\n"
        "    propagate(torch.from_numpy(pose), torch.ones(2, 6), dt)\n"
        "    twist_between(torch.from_numpy(pose), torch.from_numpy(pose), dt)\n"
        "print(len(propagate_kernel.signatures), len(twist_between_kernel.signatures))\n"
    )
    r = _run_cold(script, tmp_path)
    assert r.stdout.split() == ["1", "1"]
