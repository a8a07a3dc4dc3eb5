"""A triangle surface as plain arrays: all the solver reads of a bone or pin mesh.

Reading and checking mesh files, decimating them and finding their edges' neighbours need
trimesh, whose import alone takes about a second (it pulls in scipy.spatial). A plan
loaded for a solve therefore carries its meshes as these arrays, stored with the plan, and
turns one into a trimesh object only to build a model from it or to export it.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import trimesh

__all__ = ["Surface", "UNIT_SCALE_TO_MM", "mesh_digest"]

# The units meshes and landmarks may arrive in (everything inside slamtka is in mm).
UNIT_SCALE_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


@dataclass(frozen=True, eq=False)
class Surface:
    """Vertices (V, 3) in mm and faces (F, 3) of a processed triangle mesh."""

    vertices: np.ndarray
    faces: np.ndarray

    @staticmethod
    def of(mesh: trimesh.Trimesh) -> Surface:
        """The arrays of ``mesh`` (copies: a trimesh object may change its own later)."""
        return Surface(np.array(mesh.vertices, dtype=np.float64),
                       np.array(mesh.faces, dtype=np.int64))

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) lower and upper corners of the bounding box, mm."""
        return np.vstack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extents(self) -> np.ndarray:
        """Sides (3,) of the bounding box, mm."""
        return self.bounds[1] - self.bounds[0]

    @cached_property
    def is_watertight(self) -> bool:
        """Closed and consistently wound, as trimesh decides it (building a distance field
        finds the inside by pseudonormals then, else by winding numbers)."""
        return bool(self.to_trimesh().is_watertight)

    def to_trimesh(self) -> trimesh.Trimesh:
        """A trimesh object of these arrays, unchanged (``process=False``)."""
        import trimesh  # ~1 s to import: only building models and exporting need it

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def mesh_digest(meshes: Sequence[Surface]) -> str:
    """sha256 over the vertices and faces of ``meshes`` (in order)."""
    h = hashlib.sha256()
    for mesh in meshes:
        h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()
