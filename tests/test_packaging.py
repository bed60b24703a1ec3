"""The wheel a user installs: it ships the default config, the type marker and the licence, and its
metadata gives version ranges (no exact torch pin) with the OpenGL renderer as an extra."""

import shutil
import subprocess
import sys
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """A wheel built from a copy of the tracked files (so the build leaves nothing in the checkout), with the
    setuptools of the environment (the dev extra requires one that reads the SPDX licence fields)."""
    tmp = tmp_path_factory.mktemp("wheel")
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    src = tmp / "src"
    for name in filter(None, files.decode().split("\0")):
        if (ROOT / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp / "dist"), str(src)], check=True, capture_output=True)
    (path,) = (tmp / "dist").glob("torchevtrack-*.whl")
    return zipfile.ZipFile(path)


def test_wheel_ships_config_type_marker_kernel_manifest_and_licence(wheel):
    names = set(wheel.namelist())
    assert "torchevtrack/configs/default.yaml" in names
    assert "torchevtrack/py.typed" in names
    assert "torchevtrack/kernels.json" in names  # the parallel cold compile's manifest
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)


def test_wheel_metadata_has_ranges_and_the_gl_extra(wheel):
    (meta,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    msg = Parser().parsestr(wheel.read(meta).decode())
    assert msg["License-Expression"] == "MIT"
    requires = msg.get_all("Requires-Dist")
    torch = [r for r in requires if r.startswith("torch") and not r.startswith("torch-")]
    assert torch and "==" not in torch[0] and "<3" in torch[0]
    pyrender = [r for r in requires if r.startswith("pyrender")]
    assert pyrender and all('extra == "gl"' in r for r in pyrender)
    assert "gl" in msg.get_all("Provides-Extra")


def test_default_yaml_is_the_packaged_file():
    from torchevtrack.config import DEFAULT_YAML

    assert DEFAULT_YAML.is_file() and DEFAULT_YAML.parent.parent.name == "torchevtrack"


def test_build_outputs_are_ignored_by_git():
    ignored = subprocess.run(["git", "check-ignore", "build/x", "dist/x"], cwd=ROOT, capture_output=True, text=True)
    assert ignored.stdout.split() == ["build/x", "dist/x"]


def test_constraints_pin_every_direct_dependency_to_one_version():
    """`make` installs from constraints.txt: every dependency of the package and its extras is pinned there."""
    import tomllib

    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    reqs += [Requirement(r) for extra in project["optional-dependencies"].values() for r in extra]
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pins[name.lower().replace("_", "-")] = version
    for r in reqs:
        name = r.name.lower().replace("_", "-")
        assert name in pins, f"{name} is not pinned in constraints.txt"
        assert r.specifier.contains(pins[name]), f"{name}=={pins[name]} is outside {r.specifier}"
