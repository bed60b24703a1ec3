"""Write ``torchevtrack/kernels.json``: the kernels a tracking run calls from Python, their argument types and
their compile times, which the parallel cold compile (``torchevtrack.kernels.compile_cold``) hands to its workers.

Runs ``torchevtrack.kernels.warmup`` in one process from an empty numba cache (a temporary ``NUMBA_CACHE_DIR``, so
the package's own cache is left alone), times each compilation started from Python (callees included) with numba's
compile events; warms up again from that cache to list the signatures called from Python (a kernel first compiled
as another's callee is one of them too); writes the manifest, largest compile time first. Takes about 150 s on an
idle core. Run it after changing a kernel's arguments; ``tests/test_kernels.py`` fails while the manifest is out of
date.

    python tools/kernel_manifest.py
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def compile_times() -> dict:
    """In this process (whose cache must be empty): warm up serially and time every compilation started from
    Python, callees included; ``{(name, signature json): seconds}``."""
    from numba.core import event

    from torchevtrack.kernels import encode_signature, warmup

    depth, started, times = [0], {}, {}

    class Timer(event.Listener):
        def on_start(self, ev):
            depth[0] += 1
            if depth[0] == 1:
                started["t"] = time.perf_counter()

        def on_end(self, ev):
            depth[0] -= 1
            if depth[0] == 0:
                d = ev.data["dispatcher"]
                key = f"{d.py_func.__module__}.{d.py_func.__qualname__} {json.dumps(encode_signature(ev.data['args']))}"
                times[key] = times.get(key, 0.0) + time.perf_counter() - started["t"]

    event.register("numba:compile", Timer())
    warmup(progress=False, jobs=1)
    return times


def called_from_python() -> list:
    """In this process (whose cache is warm): warm up and list the signatures called from Python."""
    from torchevtrack.kernels import loaded_signatures, warmup

    warmup(progress=False, jobs=1)
    return loaded_signatures()


def main() -> int:
    child = os.environ.get("KERNEL_MANIFEST_STEP")
    if child:
        result = compile_times() if child == "times" else called_from_python()
        Path(os.environ["KERNEL_MANIFEST_OUT"]).write_text(json.dumps(result))
        return 0
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    with tempfile.TemporaryDirectory() as tmpdir:
        results = {}
        for step in ("times", "calls"):
            results[step] = Path(tmpdir) / f"{step}.json"
            env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmpdir) / "cache"), "KERNEL_MANIFEST_STEP": step,
                   "KERNEL_MANIFEST_OUT": str(results[step]), "PYTHONPATH": str(ROOT)}
            if step == "times":
                print("compiling every kernel once, serially, from an empty cache (about 150 s)...", file=sys.stderr)
            if subprocess.run([sys.executable, __file__], env=env).returncode:
                return 1
        times = json.loads(results["times"].read_text())
        calls = json.loads(results["calls"].read_text())
    kernels = sorted(({"name": name, "signature": sig, "seconds": round(times.get(f"{name} {json.dumps(sig)}", 0.0), 2)}
                      for name, sig in calls), key=lambda e: (-e["seconds"], e["name"]))
    path = ROOT / "torchevtrack" / "kernels.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text('{"kernels": [\n' + ",\n".join(json.dumps(e) for e in kernels) + "\n]}\n")  # a kernel a line
    tmp.replace(path)
    print(f"{path}: {len(kernels)} kernels, {sum(e['seconds'] for e in kernels):.0f} s of compilation",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
