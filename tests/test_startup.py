"""Start-up: `import torchevtrack` loads no OpenGL, numba or tracker and sets no environment variable; the
command line imports only the module of the command it runs; object names have a listing and suggestions."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "PYOPENGL_PLATFORM"}
    env["PYTHONPATH"] = str(ROOT)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env,
                          timeout=600).stdout


def _loaded_after(statement: str) -> dict:
    return json.loads(_python(
        "import os, sys, json\n"
        "env = dict(os.environ)\n"
        f"{statement}\n"
        "mods = sorted(m.split('.')[0] for m in sys.modules)\n"
        "print(json.dumps({'modules': mods, 'env_changed': sorted(set(os.environ.items()) ^ set(env.items()))}))"
    ))


def test_import_loads_no_opengl_numba_or_torch_and_sets_no_environment():
    r = _loaded_after("import torchevtrack")
    assert not {"pyrender", "OpenGL", "numba", "torch", "trimesh", "kornia"} & set(r["modules"])
    assert r["env_changed"] == []


def test_tracker_import_loads_no_opengl_and_sets_no_environment():
    r = _loaded_after("from torchevtrack import EventPoseTracker, OnlineTracker")
    assert "torch" in r["modules"]
    assert not {"pyrender", "OpenGL"} & set(r["modules"])
    assert r["env_changed"] == []


def test_help_imports_no_command_module():
    r = _loaded_after(
        "import contextlib, io\n"
        "from torchevtrack.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    main(['--help'])"
    )
    assert not {"torch", "numba", "pyrender", "trimesh"} & set(r["modules"])


def test_command_table_matches_the_modules_registrations():
    """COMMANDS names, for each command, the module that registers it (and no module registers others)."""
    import argparse
    import importlib

    from torchevtrack.cli import COMMANDS

    for module in sorted({m for m, _ in COMMANDS.values()}):
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(f"torchevtrack.cli.{module}").register(sub)
        assert set(sub.choices) == {c for c, (m, _) in COMMANDS.items() if m == module}


@pytest.mark.parametrize("command", ["track", "synth-benchmark", "objects", "warmup", "eval"])
def test_each_command_has_its_own_help(command, capsys):
    from torchevtrack.cli import main

    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    assert f"usage: torchevtrack {command}" in capsys.readouterr().out


def test_objects_lists_builtin_and_ycb_names(capsys):
    from torchevtrack.cli import main

    assert main(["objects"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split()[0] for line in lines]
    assert names[:3] == ["box", "can", "bottle"]
    assert "006_mustard_bottle" in names
    assert any("'mustard_bottle'" in line for line in lines)


@pytest.mark.parametrize("name, nearest", [("mustard", "mustard_bottle"), ("boxx", "box"), ("bottel", "bottle")])
def test_a_wrong_object_name_suggests_the_nearest(name, nearest):
    from torchevtrack.mesh import load_mesh

    with pytest.raises(ValueError, match=f"unknown object '{name}': did you mean '{nearest}'") as e:
        load_mesh(name)
    assert "\n" not in str(e.value)


def test_cli_object_name_error_is_one_line(capsys):
    from torchevtrack.cli import main

    assert main(["synth", "--object", "mustard", "--out", "/nonexistent/never"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "did you mean 'mustard_bottle'" in err


def test_a_missing_optional_extra_is_a_one_line_error(monkeypatch, capsys):
    """Without pyrender (the gl extra), the simulator's renderer says how to install it, in one line."""
    import torchevtrack.render as render

    monkeypatch.setattr(render, "pyrender", None)
    monkeypatch.setitem(sys.modules, "pyrender", None)  # `import pyrender` now raises ImportError
    monkeypatch.setitem(sys.modules, "pyrender.renderer", None)
    from torchevtrack.cli import main

    assert main(["synth", "--object", "box", "--out", str(Path("/nonexistent/never")), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pip install 'torchevtrack[gl]'" in err
