"""A hand-like occluder that holds an object at one end: palm, four fingers, a thumb and a forearm.

The hand is built in the object's frame from its bounding box and moves rigidly with it, so a simulator
renders object and hand as one mesh at the object's poses (:func:`with_hand`) while the ground truth and the
saved mesh stay the object's. Geometry (metres, object frame, bounding box ``[-e/2, e/2]``):

* the grip axis ``a`` is the box's longest axis; the palm (a box 0.02 thick, up to 0.09 x 0.09) lies against
  the ``-a`` end face;
* four fingers (capsules of radius 0.009, 0.02 apart) run along ``+a`` over the ``+c`` face (``c`` the
  shortest axis), the thumb over the ``-c`` face; their length is 50 % of the object's extent along ``a``,
  clipped to 0.04-0.10 m, so they hide a part of the silhouette whatever the object's size;
* the forearm (a capsule of radius 0.025, 0.5 m long) leaves the palm along ``-a``, tilted 30 degrees
  towards ``-c``: at the working distances of the simulator it leaves the image.

Seen from random directions at 0.7 m, the hand hides a median 6-41 % of an object's silhouette (median over
the wide suite's 12 objects: 19 %; least for the large flat boxes); when the forearm points at the camera it
hides nearly all of it. The simulator records the fraction per sequence.

The hand carries its own grey (vertex colours of luminance ``HAND_ALBEDO``), darker than the default object
albedo, so its edges against the object make events too.

Example:
    >>> import trimesh
    >>> hand = make_hand(trimesh.creation.box((0.06, 0.08, 0.2)))
    >>> hand.forearm_radius, round(float(hand.forearm_segment[1, 2] - hand.forearm_segment[0, 2]), 3)
    (0.025, -0.433)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from torchevtrack.render import DEFAULT_ALBEDO

__all__ = ["HAND_ALBEDO", "Hand", "make_hand", "with_hand"]

HAND_ALBEDO = 0.45
_SKIN = np.array([0.58, 0.40, 0.33])  # luminance 0.45 (0.299 R + 0.587 G + 0.114 B)
_FINGER_RADIUS = 0.009
_FINGER_PITCH = 0.02
_PALM = (0.02, 0.09)  # thickness, largest side
_FOREARM_RADIUS = 0.025
_FOREARM_LENGTH = 0.5
_FOREARM_TILT = math.radians(30.0)


@dataclass
class Hand:
    """A hand holding an object, in the object's frame (metres).

    Attributes:
        grip: palm, fingers and thumb, one watertight-part mesh with the hand's vertex colours.
        forearm: the forearm capsule, with the hand's vertex colours.
        forearm_segment: ``(2, 3)`` float64 end points of the forearm's axis (palm end first).
        forearm_radius: metres.
    """

    grip: trimesh.Trimesh
    forearm: trimesh.Trimesh
    forearm_segment: np.ndarray
    forearm_radius: float

    @property
    def mesh(self) -> trimesh.Trimesh:
        """Grip and forearm as one mesh."""
        return trimesh.util.concatenate([self.grip, self.forearm])


def _capsule(p0: np.ndarray, p1: np.ndarray, radius: float) -> trimesh.Trimesh:
    """Capsule whose axis runs from ``p0`` to ``p1``."""
    d = np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)
    length = float(np.linalg.norm(d))
    cap = trimesh.creation.capsule(height=length, radius=radius, count=[12, 12])
    T = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], d / length)
    T[:3, 3] = 0.5 * (np.asarray(p0) + np.asarray(p1))
    cap.apply_transform(T)
    return cap


def _painted(mesh: trimesh.Trimesh, rgb: np.ndarray) -> trimesh.Trimesh:
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.tile(np.append(rgb, 1.0) * 255.0,
                                                                          (len(mesh.vertices), 1)).round().astype(np.uint8))
    return mesh


def make_hand(obj: trimesh.Trimesh) -> Hand:
    """The hand holding ``obj`` at the ``-a`` end of its bounding box (module docstring)."""
    lo, hi = np.asarray(obj.bounds, dtype=np.float64)
    centre, ext = 0.5 * (lo + hi), hi - lo
    a, b, c = (int(i) for i in np.argsort(-ext, kind="stable"))  # longest, middle, shortest axis
    ea, eb, ec = ext[a], ext[b], ext[c]

    def along(pa: float, pb: float, pc: float) -> np.ndarray:
        """The point with coordinates ``pa, pb, pc`` on the axes ``a, b, c``."""
        p = np.empty(3)
        p[a], p[b], p[c] = pa, pb, pc
        return p

    parts = []
    thick, side = _PALM
    palm_extent = np.zeros(3)
    palm_extent[a], palm_extent[b], palm_extent[c] = thick, min(side, eb + 0.02), min(side, ec + 2 * _FINGER_RADIUS + 0.02)
    palm = trimesh.creation.box(extents=palm_extent)
    palm.apply_translation(along(centre[a] - ea / 2 - thick / 2, centre[b], centre[c]))
    parts.append(palm)
    length = float(np.clip(0.5 * ea, 0.04, 0.1))
    start, end = centre[a] - ea / 2 - thick / 2, centre[a] - ea / 2 + length
    r = _FINGER_RADIUS
    for k in range(4):
        pb = centre[b] + (k - 1.5) * _FINGER_PITCH
        parts.append(_capsule(along(start, pb, centre[c] + ec / 2 + r), along(end, pb, centre[c] + ec / 2 + r), r))
    parts.append(_capsule(along(start, centre[b], centre[c] - ec / 2 - r),
                          along(centre[a] - ea / 2 + 0.8 * length, centre[b], centre[c] - ec / 2 - r), 1.1 * r))
    grip = _painted(trimesh.util.concatenate(parts), _SKIN)

    p0 = along(centre[a] - ea / 2 - thick / 2, centre[b], centre[c])
    direction = np.zeros(3)
    direction[a], direction[c] = -math.cos(_FOREARM_TILT), -math.sin(_FOREARM_TILT)
    p1 = p0 + _FOREARM_LENGTH * direction
    forearm = _painted(_capsule(p0, p1, _FOREARM_RADIUS), _SKIN)
    return Hand(grip, forearm, np.stack((p0, p1)), _FOREARM_RADIUS)


def with_hand(obj: trimesh.Trimesh, hand: Hand) -> trimesh.Trimesh:
    """Object and hand as one mesh for rendering.

    A textured object (``TextureVisuals`` with UVs and an image) keeps its texture: the image moves into the
    top-left quarter of one twice its size whose rest is skin, where the hand's UVs point (the object's UVs are
    halved accordingly). Otherwise the
    result is vertex-coloured, an uncoloured object getting the renderers' default grey ``DEFAULT_ALBEDO``.
    """
    if obj.visual.kind == "texture":
        return _textured_with_hand(obj, hand)
    body = obj.copy()
    if body.visual.kind != "vertex":
        grey = np.full((len(body.vertices), 4), 255, dtype=np.uint8)
        grey[:, :3] = round(DEFAULT_ALBEDO * 255)
        body.visual = trimesh.visual.ColorVisuals(body, vertex_colors=grey)
    return trimesh.util.concatenate([body, hand.grip, hand.forearm])


def _texture_image(visual) -> np.ndarray:
    """The RGB texture image of ``TextureVisuals`` as ``(H, W, 3)`` uint8 (SimpleMaterial or PBRMaterial)."""
    mat = visual.material
    image = getattr(mat, "image", None)
    if image is None:
        image = getattr(mat, "baseColorTexture", None)
    if image is None:
        raise ValueError("a textured mesh needs a texture image")
    return np.asarray(image.convert("RGB"), dtype=np.uint8)


def _textured_with_hand(obj: trimesh.Trimesh, hand: Hand) -> trimesh.Trimesh:
    """The object's image in the top-left quarter of one twice as large (powers of two stay powers of two, so
    mipmaps stay exact), the rest skin; the hand's UVs point into the skin."""
    from PIL import Image

    img = _texture_image(obj.visual)
    h, w = img.shape[:2]
    image = np.empty((2 * h, 2 * w, 3), dtype=np.uint8)
    image[:] = np.round(_SKIN * 255.0).astype(np.uint8)
    image[:h, :w] = img
    uv = 0.5 * np.asarray(obj.visual.uv, dtype=np.float64)
    uv[:, 1] += 0.5  # v points up: the image's top rows are v in [0.5, 1]
    parts = [hand.grip, hand.forearm]
    hand_uv = np.tile([0.75, 0.25], (sum(len(m.vertices) for m in parts), 1))
    geometry = trimesh.util.concatenate([trimesh.Trimesh(obj.vertices, obj.faces, process=False)]
                                        + [trimesh.Trimesh(m.vertices, m.faces, process=False) for m in parts])
    geometry.visual = trimesh.visual.TextureVisuals(uv=np.concatenate((uv, hand_uv)), image=Image.fromarray(image))
    return geometry
