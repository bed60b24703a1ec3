"""A benchmark sequence on disk: events, camera, ground-truth poses, mesh and metadata.

Directory layout (see README "Sequence directory format")::

    events.h5     x, y (int16), t (int64 us), p (int8) -- torchevtrack.io.events_h5
    camera.json   width, height, fx, fy, cx, cy
    gt_poses.txt  TUM "t tx ty tz qx qy qz qw" (seconds), object in camera frame
    mesh.ply      the mesh the poses refer to (metres)
    meta.json     object, motion group, seed, measured speeds, generator parameters, version

and, for an object the simulator printed a texture on, the model with that print (optional)::

    mesh_textured.glb   the same geometry with its UVs and texture image (glTF binary)

Example:
    >>> seq = Sequence.load("runs/mustard_regular")        # doctest: +SKIP
    >>> len(seq.events), seq.camera.width, seq.gt_poses.shape  # doctest: +SKIP
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchevtrack.camera import Camera
from torchevtrack.events import EventStream
from torchevtrack.io.atomic import replacing, write_text
from torchevtrack.io.events_h5 import read_events_h5, write_events_h5
from torchevtrack.io.poses import read_tum, write_tum

if TYPE_CHECKING:  # trimesh takes a second or two to import: only reading a mesh does (`info` never)
    import trimesh

__all__ = ["Sequence", "SEQUENCE_FILES", "TEXTURED_MESH"]

SEQUENCE_FILES = ("events.h5", "camera.json", "gt_poses.txt", "mesh.ply", "meta.json")
TEXTURED_MESH = "mesh_textured.glb"
"""The optional sixth file: the object with the texture printed on it (the untextured ``mesh.ply`` is a CAD model's
geometry; this one is a textured scan's, as YCB's and BOP's models come)."""


@dataclass
class Sequence:
    """One sequence in memory.

    Attributes:
        events: time-sorted events inside the camera's sensor.
        camera: pinhole camera.
        gt_t_us: ``(M,)`` int64 ground-truth timestamps, microseconds.
        gt_poses: ``(M, 7)`` float64 ground-truth poses (object in camera frame).
        mesh: the object mesh the poses refer to (metres).
        meta: JSON-serialisable metadata.
        textured_mesh: the object as printed (``mesh``'s geometry with a ``TextureVisuals``), or ``None``.
    """

    events: EventStream
    camera: Camera
    gt_t_us: torch.Tensor
    gt_poses: torch.Tensor
    mesh: trimesh.Trimesh
    meta: dict = field(default_factory=dict)
    textured_mesh: trimesh.Trimesh | None = None

    def save(self, directory: str | Path) -> Path:
        """Write the five files, and :data:`TEXTURED_MESH` if there is a textured mesh, into ``directory`` (created if
        needed); returns the directory."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        write_events_h5(d / "events.h5", self.events, width=self.camera.width, height=self.camera.height)
        self.camera.save(d / "camera.json")
        write_tum(d / "gt_poses.txt", self.gt_t_us, self.gt_poses)
        with replacing(d / "mesh.ply") as tmp:
            self.mesh.export(tmp, file_type="ply", encoding="binary")
        if self.textured_mesh is not None:
            with replacing(d / TEXTURED_MESH) as tmp:
                self.textured_mesh.export(tmp, file_type="glb")
        write_text(d / "meta.json", json.dumps(self.meta, indent=2, sort_keys=True) + "\n")
        return d

    @classmethod
    def load(cls, directory: str | Path) -> "Sequence":
        """Read and validate a sequence directory.

        Raises:
            FileNotFoundError: the directory or one of its files is missing (the message names it).
            TypeError / ValueError: wrong dtypes, unsorted times, events outside the sensor (the message
                names the event index), malformed camera, poses or metadata.
        """
        d = Path(directory)
        if not d.is_dir():
            raise FileNotFoundError(f"sequence directory not found: {d}")
        for name in SEQUENCE_FILES:
            if not (d / name).is_file():
                raise FileNotFoundError(f"sequence {d} lacks {name}")
        camera = Camera.load(d / "camera.json")
        events = read_events_h5(d / "events.h5", width=camera.width, height=camera.height)
        gt_t_us, gt_poses = read_tum(d / "gt_poses.txt")
        if gt_t_us.numel() < 2:
            raise ValueError(f"{d / 'gt_poses.txt'}: need at least two poses")
        if (gt_poses[:, 2] <= 0).any():
            raise ValueError(f"{d / 'gt_poses.txt'}: a pose places the object behind the camera (tz <= 0)")
        mesh = _read_mesh(d / "mesh.ply")
        textured = _read_mesh(d / TEXTURED_MESH) if (d / TEXTURED_MESH).is_file() else None
        try:
            meta = json.loads((d / "meta.json").read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{d / 'meta.json'}: not valid JSON ({e})") from None
        if not isinstance(meta, dict):
            raise ValueError(f"{d / 'meta.json'}: expected a JSON object")
        return cls(events, camera, gt_t_us, gt_poses, mesh, meta, textured)


def _read_mesh(path: Path) -> trimesh.Trimesh:
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise ValueError(f"{path}: unreadable mesh ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: empty mesh")
    return mesh
