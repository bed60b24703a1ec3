"""A printed-looking packaging texture on any mesh: random colour blocks, stripes and text-like marks.

:func:`printed_texture` returns the same geometry carrying a ``trimesh`` :class:`~trimesh.visual.TextureVisuals`
(UV coordinates and a PIL image), the form textured models (e.g. YCB's) come in, so both renderers
(:mod:`torchevtrack.render`, :mod:`torchevtrack.raster`) draw its luminance times their Lambert shading and a
simulated camera sees events inside the silhouette, as on real packaging.

UV mapping (box projection, robust for any mesh): each face is projected along the axis its normal is most
aligned with (six directions, +-x, +-y, +-z) onto the other two axes, scaled by the mesh's largest extent, into its
own square cell of a 3 x 3 grid of the image (six cells used), so opposite sides show different prints. Vertices
shared by faces of different directions are split (each face's corners get that face's UVs); the positions and
the faces (their order and winding) are those of the input.

Example:
    >>> from torchevtrack.mesh import load_mesh
    >>> from torchevtrack.synth.texture import printed_texture
    >>> box = printed_texture(load_mesh("box"), seed=3, size=256)
    >>> box.visual.kind, box.visual.material.image.size, len(box.faces) == len(load_mesh("box").faces)
    ('texture', (256, 256), True)
"""

from __future__ import annotations

import numpy as np
import trimesh
from PIL import Image, ImageDraw

__all__ = ["printed_texture"]

# printing inks (RGB 0-255): light papers, saturated colours and dark inks, so neighbouring areas contrast
_PAPERS = ((244, 240, 228), (250, 250, 250), (238, 214, 120), (206, 226, 240))
_COLOURS = ((200, 30, 30), (20, 60, 150), (240, 190, 20), (30, 120, 50), (235, 110, 20), (120, 30, 110))
_INKS = ((15, 15, 20), (40, 30, 90), (110, 10, 10))
_GRID = 3  # cells per image side; six of the nine hold the six projection directions
_INSET = 0.04  # fraction of a cell left as margin around the mapped area (no bleeding across cells in mipmaps)


def printed_texture(mesh: trimesh.Trimesh, seed: int, size: int = 512) -> trimesh.Trimesh:
    """The geometry of ``mesh`` with box-projected UVs and a random printed packaging texture.

    Args:
        mesh: a triangle mesh (metres); its visuals are replaced.
        seed: the texture is a deterministic function of ``seed`` (and ``size``).
        size: side of the square texture image in pixels (>= 48); a power of two keeps GPU and CPU mipmaps equal.

    Returns:
        A new ``trimesh.Trimesh``: vertices ``(V', 3)`` (the input's, split where faces of different projection
        directions meet), faces ``(F, 3)`` (same order and winding), ``visual`` a
        :class:`~trimesh.visual.TextureVisuals` with ``uv`` ``(V', 2)`` in ``[0, 1]`` (``v`` up, the OBJ/glTF
        convention) and an RGB ``size x size`` PIL image.

    Raises:
        TypeError: ``mesh`` is not a Trimesh; ValueError: no faces or ``size < 48``.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 48:
        raise ValueError(f"size must be an integer >= 48 pixels, got {size!r}")
    size = int(size)
    vertices, faces, uv = _box_uv(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), size)
    image = _print_image(np.random.default_rng(seed), size)
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    return trimesh.Trimesh(vertices, faces, visual=visual, process=False)


def _box_uv(vertices: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box projection: split vertices ``(V', 3)``, faces ``(F, 3)`` and their UVs ``(V', 2)`` in ``[0, 1]``."""
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    axis = np.abs(normal).argmax(axis=1)
    direction = 2 * axis + (normal[np.arange(len(faces)), axis] > 0)  # 0..5: -x, +x, -y, +y, -z, +z
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    scale = max(float((hi - lo).max()), 1e-12)
    centre = (lo + hi) / 2
    # one new vertex per (vertex, direction) pair in use
    key = faces.astype(np.int64) * 6 + direction[:, None]
    unique, inverse = np.unique(key.reshape(-1), return_inverse=True)
    vid, vdir = unique // 6, unique % 6
    k = vdir // 2
    i, j = (k + 1) % 3, (k + 2) % 3  # the two axes of the projection plane
    p = (vertices[vid] - centre) / scale + 0.5  # in [0, 1] along every axis
    a, b = p[np.arange(len(vid)), i], p[np.arange(len(vid)), j]
    cell = size // _GRID
    col, row = vdir % _GRID, vdir // _GRID
    x = (col + _INSET + a * (1 - 2 * _INSET)) * cell  # image pixel coordinates, rows top-down
    y = (row + _INSET + (1 - b) * (1 - 2 * _INSET)) * cell
    uv = np.stack((x / size, 1.0 - y / size), axis=1)
    return vertices[vid], inverse.reshape(faces.shape), uv


def _print_image(rng: np.random.Generator, size: int) -> Image.Image:
    """An RGB ``size x size`` image: one printed design per grid cell."""
    image = Image.new("RGB", (size, size), _PAPERS[0])
    draw = ImageDraw.Draw(image)
    cell = size // _GRID
    for n in range(_GRID * _GRID):
        x0, y0 = (n % _GRID) * cell, (n // _GRID) * cell
        _print_cell(draw, rng, x0, y0, cell)
    return image


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _print_cell(draw: ImageDraw.ImageDraw, rng: np.random.Generator, x0: int, y0: int, c: int) -> None:
    """One packaging side in the ``c x c`` square at ``(x0, y0)``: a paper colour, colour blocks, a band of
    stripes, a logo disc and lines of text-like marks."""

    def rect(u0, v0, u1, v1, colour):  # fractions of the cell; at least one pixel (Pillow rejects an inverted box)
        left, top = x0 + u0 * c, y0 + v0 * c
        draw.rectangle((left, top, max(x0 + u1 * c - 1, left), max(y0 + v1 * c - 1, top)), fill=colour)

    paper = _pick(rng, _PAPERS)
    rect(0, 0, 1, 1, paper)
    for _ in range(int(rng.integers(1, 4))):  # colour blocks
        w, h = rng.uniform(0.2, 0.6, 2)
        u, v = rng.uniform(0, 1 - w), rng.uniform(0, 1 - h)
        rect(u, v, u + w, v + h, _pick(rng, _COLOURS))
    # a band of parallel stripes across the cell
    v, colour = rng.uniform(0.05, 0.8), _pick(rng, _COLOURS + _INKS)
    for _ in range(int(rng.integers(2, 6))):
        w = rng.uniform(0.015, 0.05)
        rect(0, v, 1, v + w, colour)
        v += w + rng.uniform(0.015, 0.05)
    # a logo disc
    r = rng.uniform(0.06, 0.15)
    u, v = rng.uniform(r, 1 - r, 2)
    draw.ellipse((x0 + (u - r) * c, y0 + (v - r) * c, x0 + (u + r) * c, y0 + (v + r) * c), fill=_pick(rng, _INKS))
    # lines of text-like marks: words of dark ink on a light patch
    h = rng.uniform(0.025, 0.045)
    lines = int(rng.integers(2, 6))
    u0, v0 = rng.uniform(0.03, 0.3), rng.uniform(0.03, 1 - lines * 2 * h - 0.03)
    u1 = u0 + rng.uniform(0.4, 0.65)
    rect(u0 - 0.02, v0 - h / 2, u1 + 0.02, v0 + (lines * 2 - 0.5) * h, _pick(rng, _PAPERS))
    ink = _pick(rng, _INKS)
    for line in range(lines):
        u, v = u0, v0 + 2 * h * line
        while True:
            w = rng.uniform(0.03, 0.12)
            if u + w > u1:
                break
            rect(u, v, u + w, v + h, ink)
            u += w + rng.uniform(0.015, 0.03)
