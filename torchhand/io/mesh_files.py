"""Object meshes given by a user (``.ply``, ``.obj``, ``.off``, ``.stl``), read with
trimesh and checked for what scanning and rigid models need: a closed surface, in
millimetres, of a hand-held size.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from torchhand.io.thesis import FormatError

__all__ = ["check_mesh", "ObjectMesh", "read_object_mesh", "write_mesh", "MESH_SUFFIXES", "HAND_HELD_MM"]

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl")
#: the largest extent (mm) of an object a hand can hold and turn, and the smallest that
#: is not a mesh in metres (a 10 mm object is small for a hand; 10 units of a mesh in
#: metres would be a 10 m object)
HAND_HELD_MM = (10.0, 400.0)


class ObjectMesh(NamedTuple):
    """vertices: (V, 3) float64 mm; faces: (F, 3) int64; path: where it was read."""

    vertices: np.ndarray
    faces: np.ndarray
    path: Optional[Path]

    @property
    def extent(self) -> np.ndarray:
        """(3,) the axis-aligned size in mm."""
        return self.vertices.max(0) - self.vertices.min(0)


def read_object_mesh(path, closed: bool = True, size_mm=HAND_HELD_MM) -> ObjectMesh:
    """Read a triangle mesh in mm and check it.

    Raises FormatError naming the file when it cannot be read, is empty, is not closed
    (``closed``: watertight and consistently oriented, as a solid needs), or has a
    largest extent outside ``size_mm`` (below: most likely metres, the message says so;
    above: not an object a hand holds).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise FormatError(f"{path}: expected a mesh file ({', '.join(MESH_SUFFIXES)}), got {path.suffix!r}")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many kinds
        raise FormatError(f"{path}: not a readable mesh ({err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise FormatError(f"{path}: holds no triangles")
    check_mesh(mesh, path, closed, size_mm)
    if closed and mesh.volume < 0:
        mesh.invert()  # inward-facing triangles: the same solid
    return ObjectMesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), path)


def check_mesh(mesh, what, closed: bool = True, size_mm=HAND_HELD_MM) -> None:
    """Raise FormatError naming ``what`` when a trimesh mesh has a largest extent outside
    ``size_mm`` (below: most likely metres) or, with ``closed``, is not watertight with a
    consistent winding."""
    extent = float((mesh.vertices.max(0) - mesh.vertices.min(0)).max())
    lo, hi = size_mm
    if extent < lo:
        raise FormatError(f"{what}: largest extent {extent:.4g} units; meshes are read in mm, and an object "
                          f"under {lo:g} mm looks like a mesh in metres: scale it by 1000")
    if extent > hi:
        kind = "a hand-held object" if hi == HAND_HELD_MM[1] else "an object here"
        raise FormatError(f"{what}: largest extent {extent:.4g} mm; {kind} is at most {hi:g} mm")
    if closed and not (mesh.is_watertight and mesh.is_winding_consistent):
        raise FormatError(f"{what}: the mesh is not closed (watertight: {mesh.is_watertight}, consistent "
                          f"winding: {mesh.is_winding_consistent}); close its holes first, e.g. with "
                          "trimesh.repair.fill_holes or a Poisson reconstruction")


def write_mesh(path, vertices: np.ndarray, faces: np.ndarray, colors: Optional[np.ndarray] = None) -> Path:
    """Write a triangle mesh (PLY, OBJ or OFF by the suffix); ``colors``: optional (V, 3)
    uint8 per-vertex colours. Returns the path."""
    import trimesh

    path = Path(path)
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False,
                           vertex_colors=colors)
    mesh.export(path)
    return path
