"""The kernels' cache: a cold cache is detected (from an empty NUMBA_CACHE_DIR), announced once in one line and
compiled by worker processes from the shipped manifest, which lists what a tracking run calls; `warmup` leaves no
module of the tracker cold; a kernel called from Python and from compiled steps compiles once."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _printed_json(script: str):
    """The JSON value that ``script``, run in a fresh Python process (the package's own cache), printed last."""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=900, check=True)
    return json.loads(out.stdout.splitlines()[-1])


def _run_cold(script: str, cache_dir: Path, *args: str) -> subprocess.CompletedProcess:
    """``script`` (with ``args``) in a fresh Python process whose numba cache is ``cache_dir``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache_dir)}
    return subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, env=env, timeout=600,
                          check=True)


def test_a_cold_cache_is_announced_once_and_compiled_by_workers_before_first_use(tmp_path):
    script = (
        "import torch\n"
        "from torchevtrack.kernels import compile_cold, manifest, uncached_kernels\n"
        "from torchevtrack.stages import propagate\n"
        "cold = uncached_kernels()\n"
        "print(len(cold), sorted(e['name'] for e in manifest() if e['name'] in cold))\n"
        "print(compile_cold(jobs=2), compile_cold(jobs=2))\n"
        "print(uncached_kernels())\n"
        "propagate.propagate(torch.tensor([[0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0]]), torch.ones(1, 6), 0.002)\n"
        "stats = propagate.propagate_kernel.stats\n"
        "print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))\n"
    )
    r = _run_cold(script, tmp_path)
    cold, compiled, after, hits_misses = r.stdout.splitlines()
    assert cold == ("14 ['torchevtrack.geometry.nb_normalise_quaternions', "
                    "'torchevtrack.stages.propagate._invalid_kernel', "
                    "'torchevtrack.stages.propagate.propagate_kernel']")
    # the manifest's entry points of the cold modules, by two workers (also the events module's, whose cache directory
    # holds the lock that keeps processes starting cold at once from compiling twice); once per process
    assert compiled == "4 0"
    assert after == "['torchevtrack.stages.canvas_taps']"  # the package's helper, called from modules not loaded
    assert hits_misses == "1 0"  # this process loaded the workers' code instead of compiling
    notice = r.stderr.strip().splitlines()
    assert len(notice) == 1, notice
    assert notice[0].startswith("torchevtrack: compiling 16 numba kernels on first use in 2 processes")
    assert "torchevtrack warmup" in notice[0]


def test_a_process_starting_cold_waits_for_the_one_compiling(tmp_path):
    import fcntl
    import time

    script = (
        "from torchevtrack.kernels import compile_cold\n"
        "from torchevtrack.stages import propagate\n"
        "print(compile_cold(jobs=2))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path)}
    probe = _run_cold("from torchevtrack.events import first_invalid; print(first_invalid.stats.cache_path)", tmp_path)
    lock_dir = Path(probe.stdout.strip())
    with open(lock_dir / "torchevtrack-compile.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # another process compiling
        child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, env=env)
        first = child.stderr.readline()
        time.sleep(1.0)
        assert child.poll() is None  # still waiting
        fcntl.flock(held, fcntl.LOCK_UN)
    out, rest = child.communicate(timeout=600)
    assert first.startswith("torchevtrack: another process is compiling the numba kernels; waiting")
    assert rest.startswith("torchevtrack: compiling 16 numba kernels")  # the lock was free, the cache still cold
    assert out.split() == ["4"]


def test_a_worker_that_fails_an_entry_goes_on_with_the_next(tmp_path):
    script = (
        "from torchevtrack.kernels import _compile_in_workers, manifest\n"
        "small = [i for i, e in enumerate(manifest()) if e['name'].endswith('nb_normalise_quaternions')]\n"
        "print(_compile_in_workers([len(manifest()), *small], 1))\n"  # an index past the manifest, then a kernel
    )
    assert _run_cold(script, tmp_path).stdout.split() == ["1"]


def test_signature_encoding_round_trips_named_tuples_and_read_only_arrays():
    import numba
    import numpy as np

    from torchevtrack.kernels import decode_signature, encode_signature
    from torchevtrack.stages.flow import FlowField

    ro = np.zeros(3)
    ro.setflags(write=False)
    field = FlowField(np.zeros((1, 2, 2), np.float32), np.zeros((1, 2, 2), np.float32), np.zeros((1, 2), np.bool_),
                      np.zeros((1, 2), np.int64))
    sig = tuple(numba.typeof(v) for v in (ro, np.float32(1), np.int64(2), np.bool_(True), None, field))
    assert decode_signature(encode_signature(sig)) == sig


def test_the_manifest_names_exactly_the_kernels_a_warm_tracking_run_calls_from_python():
    # With a warm cache, a kernel called from compiled code is never typed again: the dispatchers' signatures after
    # warmup are those called from Python, which the manifest must list (else tools/kernel_manifest.py is due).
    script = (
        "import json\n"
        "from torchevtrack.kernels import loaded_signatures, manifest, warmup\n"
        "warmup(progress=False)\n"
        "seen = [list(s) for s in loaded_signatures()]\n"
        "listed = sorted(([e['name'], e['signature']] for e in manifest()), key=json.dumps)\n"
        "print(json.dumps([seen, listed]))\n"
    )
    # the first run compiles whatever earlier tests left cold (a kernel compiled here types its callees too), the
    # second loads everything from the cache
    _printed_json(script)
    seen, listed = _printed_json(script)
    assert seen == listed, "torchevtrack/kernels.json is out of date: run python tools/kernel_manifest.py"


def test_the_manifest_holds_what_a_start_search_calls_from_python():
    # `track` searches around its start pose; where the chamfer result does not win it refines turned poses with the
    # template correction: kernels a plain tracking run never calls from Python, which a first `track` after `make
    # demo` or `warmup` compiled in the middle of its stream (20 s on 2 cores) while they were not in the manifest
    script = (
        "import json\n"
        "import numpy as np, torch\n"
        "from torchevtrack import Camera, EventPoseTracker\n"
        "from torchevtrack.config import TrackerConfig\n"
        "from torchevtrack.events import EventStream\n"
        "from torchevtrack.kernels import _warmup_events, load, loaded_signatures, manifest\n"
        "from torchevtrack.mesh import load_mesh\n"
        "from torchevtrack.raster import RasterRenderer\n"
        "from torchevtrack.recover import TURN_DEG, turned_poses\n"
        "load()\n"
        "camera, mesh = Camera(160, 120, 150.0, 150.0, 80.0, 60.0), load_mesh('box')\n"
        "events, pose0 = _warmup_events(camera, mesh, RasterRenderer, EventStream, np, torch)\n"
        "cfg = TrackerConfig().replace(loss={'enabled': True}, recover={'enabled': True, 'start_search': True})\n"
        "tracker = EventPoseTracker(camera, mesh, cfg)\n"
        "times, _ = tracker.track(events, pose0, progress=False)\n"
        "tracker.refine(turned_poses(tracker.pose[0], TURN_DEG), 0, int(times[0, -1]))\n"
        "listed = {json.dumps([e['name'], e['signature']]) for e in manifest()}\n"
        "print(json.dumps([tracker.recover.searches, sorted({n for n, s in loaded_signatures()\n"
        "                                                     if json.dumps([n, s]) not in listed})]))\n"
    )
    searches, unlisted = _printed_json(script)
    assert searches >= 1 and unlisted == []


def test_load_gives_a_process_every_kernel_of_the_manifest():
    # `live` loads them before its stream starts, so that its first updates do not wait for code to load
    script = (
        "import json\n"
        "from torchevtrack.kernels import load, loaded_signatures, manifest\n"
        "before = len(loaded_signatures())\n"
        "n = load()\n"
        "seen = {json.dumps(list(s)) for s in loaded_signatures()}\n"
        "missing = [e['name'] for e in manifest() if json.dumps([e['name'], e['signature']]) not in seen]\n"
        "print(json.dumps([before, n, len(manifest()), missing]))\n"
    )
    before, n, listed, missing = _printed_json(script)
    assert before == 0 and n == listed > 0 and missing == []


def test_warmup_leaves_no_tracker_module_cold(capsys):
    import torchevtrack.online  # noqa: F401  (the modules a tracking run loads)
    import torchevtrack.tracker  # noqa: F401
    from torchevtrack.kernels import uncached_kernels, warmup

    warmup(progress=False)
    # torchevtrack.reference holds the tests' torch/numba oracles and torchevtrack.synth the simulator, which a
    # tracking run never calls: the collected test files load them, and in a fresh cache nothing may have compiled them
    assert [n for n in uncached_kernels() if not n.startswith(("torchevtrack.reference.", "torchevtrack.synth."))] == []
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


CALLEE = "import numba\n\n\n@numba.njit(cache=True)\ndef f():\n    return {}\n"
CALLER = "import numba\n\nfrom pkgx.{callee} import {fn}\n\n\n@numba.njit(cache=True)\ndef {name}():\n    return {fn}() + {add}\n"


def _package(root: Path, guard: bool) -> None:
    """``pkgx``: ``b.f`` (a kernel), ``a.g`` calls it, ``c.h`` calls ``a.g``; its ``__init__`` runs the stale-caller
    check on import (``guard``) as torchevtrack's does, or not (numba alone)."""
    pkg = root / "pkgx"
    pkg.mkdir()
    check = "from pathlib import Path\nfrom torchevtrack.kernels import drop_stale_callers\n" \
            "print(drop_stale_callers(Path(__file__).parent, 'pkgx'))\n"
    (pkg / "__init__.py").write_text(check if guard else "")
    (pkg / "b.py").write_text(CALLEE.format(1))
    (pkg / "a.py").write_text(CALLER.format(callee="b", fn="f", name="g", add=10))
    (pkg / "c.py").write_text(CALLER.format(callee="a", fn="g", name="h", add=100))


@pytest.mark.parametrize("user_cache_dir", [False, True], ids=["in-tree", "NUMBA_CACHE_DIR"])
def test_an_edited_callee_recompiles_its_callers_in_other_modules(tmp_path, user_cache_dir):
    """Numba alone keeps a caller's cached code of a callee edited in another module (the oracle: the stale value
    after the edit); with the check on import, every module that reaches the edited one recompiles."""
    for guard in (False, True):
        root = tmp_path / f"guard{guard}"
        root.mkdir()
        cache = root / "cache" if user_cache_dir else None
        _package(root, guard)
        env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{ROOT}"}
        env.pop("NUMBA_CACHE_DIR", None)
        if cache is not None:
            env["NUMBA_CACHE_DIR"] = str(cache)

        def call() -> list[str]:
            r = subprocess.run([sys.executable, "-c", "import pkgx.b, pkgx.c\nprint(pkgx.b.f(), pkgx.c.h())"],
                               capture_output=True, text=True, env=env, timeout=300, check=True)
            return r.stdout.splitlines()

        first = call()
        (root / "pkgx" / "b.py").write_text(CALLEE.format(22))  # the callee edited; its callers' files are not
        second = call()
        if guard:
            assert first == ["[]", "1 111"]  # nothing cached yet
            assert second == ["['pkgx.a', 'pkgx.c']", "22 132"]  # both callers, the one through the other too
            assert call() == ["[]", "22 132"]  # nothing edited since
        else:
            assert first == ["1 111"]
            assert second == ["22 111"], "numba's own cache was expected to miss the edit (the test's premise)"


NEWTON = (
    "import sys, torch\n"
    "from torchevtrack.stages import template as tm\n"
    "model, starts, obs, fx, fy = torch.load(sys.argv[1])\n"
    "c = tm.newton_arrays(tm.TemplateModel(*model), starts.numpy(), obs.numpy(), fx, fy, 1.0, 0.0087266, 4)\n"
    "torch.save([torch.from_numpy(x) for x in (c.pose, c.score, c.scores, c.iterations)], sys.argv[2])\n"
    "print(sum(tm.newton_kernel.stats.cache_misses.values()), sum(tm.newton_kernel.stats.cache_hits.values()))\n"
)


def test_a_process_that_compiles_the_correction_and_one_that_loads_it_correct_alike(tmp_path):
    """The template correction (its Newton search with the score's terms summed in any order, ``fastmath``) in a
    process that compiles it and in the next, which loads the cached code: the same poses, to the bit. Numba links a
    copy of every compiled callee into each caller and optimises it again; the compiling process calls the callee's
    own code, a loading process the copy. The two differed when the callee summed in any order (14 of 100 calls of a
    tracking run, by up to 3e-14): such a callee is now inlined into its callers (the rule in
    ``torchevtrack.kernels``)."""
    import numpy as np
    import torch

    from torchevtrack import geometry as g
    from torchevtrack.camera import Camera
    from torchevtrack.config import TrackerConfig
    from torchevtrack.mesh import load_mesh
    from torchevtrack.reference import edge_map
    from torchevtrack.render import Renderer
    from torchevtrack.stages import template as tm

    camera, mesh = Camera.default(), load_mesh("006_mustard_bottle", decimate=4000)
    pose = torch.cat((torch.tensor([0.03, -0.02, 0.5]), g.quat_exp(torch.tensor([0.4, -0.6, 0.3]))))[None].double()
    gen = torch.Generator().manual_seed(3)
    B = 32
    steps = (torch.rand(B, 6, generator=gen, dtype=torch.float64) * 2 - 1) * torch.tensor([4e-3] * 3 + [0.03] * 3)
    starts = tm.apply_steps(pose, steps[None])[0]
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
    roi = tuple(int(v) for v in tm.render_window(pose, camera, radius, 24)[0])
    with Renderer(mesh, camera) as r:
        base = r.render(pose.float(), roi=roi)
    corrector = tm.TemplateCorrector.from_config(camera, TrackerConfig().template)
    model = corrector.template_model(pose, base.depth, base.gray, roi[:2])
    model = tm.TemplateModel(*(x.expand(B, *x.shape[1:]).contiguous() for x in model))
    # a decaying surface's values, over many magnitudes (sums of values of a few magnitudes are exact in any order):
    # edges, a third of the object's pixels (a texture: the area term weighs it) and some noise
    shape = (B, *base.depth.shape[1:])
    seen = edge_map(base.gray, (base.depth > 0).float()) + (base.depth > 0) * (torch.rand(shape, generator=gen) < 0.3)
    seen = (seen + (torch.rand(shape, generator=gen) < 0.02)) * torch.exp(-30 * torch.rand(shape, generator=gen))
    obs = model.observe(seen, roi[:2])
    torch.save([list(model), starts, obs, camera.fx, camera.fy], tmp_path / "in.pt")
    runs = []
    for k in range(2):
        r = _run_cold(NEWTON, tmp_path / "cache", str(tmp_path / "in.pt"), str(tmp_path / f"out{k}.pt"))
        runs.append((r.stdout.split(), torch.load(tmp_path / f"out{k}.pt")))
    assert runs[0][0] == ["1", "0"] and runs[1][0] == ["0", "1"]  # compiled, then loaded
    assert int(runs[0][1][3].sum()) > B  # the searches moved (more than one round on average)
    for a, b in zip(runs[0][1], runs[1][1]):
        assert torch.equal(a, b)


def _flags(kernel) -> set:
    """A dispatcher's ``fastmath`` flags as a set (``True``: all of LLVM's, ``"fast"``)."""
    fm = kernel.targetoptions.get("fastmath", False)
    return {"fast"} if fm is True else set(fm or ())


def _package_kernels() -> list:
    """Every cached numba dispatcher of the package, all its modules imported (an optional extra's reader may not
    import; ``__main__`` would run the command line)."""
    import importlib
    import pkgutil

    import torchevtrack
    from torchevtrack.kernels import _kernels

    for m in pkgutil.walk_packages(torchevtrack.__path__, "torchevtrack."):
        if not m.name.endswith("__main__"):
            try:
                importlib.import_module(m.name)
            except ImportError:
                pass
    return _kernels()


def test_a_kernel_whose_results_depend_on_its_optimisation_is_called_by_no_other_kernel_unless_inlined():
    """A kernel compiled with flags that let LLVM change its results (reassociation, contraction, approximate
    division or functions: beyond ``EXACT_FASTMATH``) runs as different machine code in a process that compiled it
    and in one that loaded its caller from the cache (the test above), unless numba inlines it into its callers
    (``inline="always"``), which compile it once each. Found by the names called in every kernel's source; the one
    exception sums distances whose rounding only widens bounds that hold in any order (``flow._spread_sums``)."""
    import ast
    import inspect

    from torchevtrack.kernels import EXACT_FASTMATH

    kernels = _package_kernels()
    inexact = {id(k): k for k in kernels if _flags(k) - EXACT_FASTMATH}
    assert {k.py_func.__name__ for k in inexact.values()} >= {"_quadratic_terms", "_spread_sums"}  # found at all
    called = []
    for caller in kernels:
        tree = ast.parse(inspect.getsource(caller.py_func).lstrip())
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                callee = caller.py_func.__globals__.get(node.func.id)
                if id(callee) in inexact and callee.targetoptions.get("inline") != "always":
                    called.append(f"{caller.py_func.__qualname__} -> {callee.py_func.__qualname__}")
    assert called == ["_sum_bounds -> _spread_sums"]


INHERIT = (
    "import json, sys, numba, numpy as np\n"
    "from numba.core.compiler import Flags\n"
    "from torchevtrack.linalg import eigh\n"
    "@numba.njit(fastmath=True, error_model='numpy')\n"
    "def caller(a, d, v):\n"
    "    eigh(a, d, v)\n"
    "a = np.array([[2.0, 1.0], [1.0, 3.0]])\n"
    "(caller if sys.argv[1] == 'caller' else eigh)(a.copy(), np.empty(2), np.empty((2, 2)))\n"
    "(tag,) = eigh.overloads[eigh.signatures[0]].fndesc.abi_tags\n"
    "print(json.dumps([sum(eigh.stats.cache_misses.values()), Flags.demangle(tag)]))\n"
)


def test_a_kernel_compiled_first_by_a_caller_keeps_its_own_flags(tmp_path):
    """Numba compiles a kernel that a caller's compilation reaches first with the caller's ``fastmath`` and error
    model where the kernel leaves them unset, and caches that code by argument types alone; so which caller a fresh
    install's workers compiled first changed what later processes ran (two fresh caches of one source tracked apart).
    ``linalg.eigh`` compiled first from a caller with every ``fastmath`` flag and numpy's error model gets exactly
    the flags it gets compiled alone, in a process with an empty cache each."""
    runs = {}
    for first in ("caller", "alone"):
        out = _run_cold(INHERIT, tmp_path / first, first)
        runs[first] = json.loads(out.stdout.splitlines()[-1])
    assert runs["caller"][0] == runs["alone"][0] == 1  # compiled in each process, not loaded
    assert runs["caller"][1] == runs["alone"][1]
    assert "fastmath" not in runs["caller"][1] and "error_model" not in runs["caller"][1]


def test_every_kernel_states_its_fastmath_flags_and_error_model():
    """Every compiled kernel of the package is made by ``kernels.kernel`` (or states both options itself), so no
    kernel takes a caller's (the test above)."""
    kernels = _package_kernels()
    assert len(kernels) > 100
    unstated = [k.py_func.__qualname__ for k in kernels
                if "fastmath" not in k.targetoptions or "error_model" not in k.targetoptions]
    assert unstated == []
