"""Loading and checking surface meshes (STL/PLY/OBJ) of bones and pins.

Meshes from CT segmentation arrive in whatever unit the exporting tool used (the public knee
meshes used in tests are in metres). Everything inside slamtka is in millimetres, so units are
either declared or detected from the size of the object, and a mesh that cannot be a bone or
a pin is refused with a message that says why.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from slamtka.solver.surface import UNIT_SCALE_TO_MM

__all__ = ["MeshError", "load_mesh"]

log = logging.getLogger(__name__)

_SUPPORTED_SUFFIXES = {".stl", ".ply", ".obj"}


class MeshError(ValueError):
    """A mesh file that cannot be used as a model, with the reason."""


def _detect_scale(extent: float, expected_mm: tuple[float, float], name: str) -> float:
    """Scale to mm for which the largest extent falls in the expected range."""
    for unit, scale in UNIT_SCALE_TO_MM.items():
        if expected_mm[0] <= extent * scale <= expected_mm[1]:
            if unit != "mm":
                log.warning("%s: units detected as %s (largest extent %.4g), converting to mm",
                            name, unit, extent)
            return scale
    raise MeshError(
        f"{name}: largest extent {extent:.4g} fits no unit (mm, cm, m) for an object of "
        f"{expected_mm[0]:.0f}-{expected_mm[1]:.0f} mm; declare the units or check the file"
    )


def _count_pieces(mesh: trimesh.Trimesh) -> int:
    """Number of face-connected pieces. Not ``mesh.split()``: that tries to fill the pieces'
    holes, which needs networkx (not a dependency), only to be counted."""
    components = trimesh.graph.connected_components(
        mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), engine="scipy")
    return len(components)


def load_mesh(
    path: str | Path,
    expected_extent_mm: tuple[float, float],
    units: str = "auto",
    require_watertight: bool = False,
) -> trimesh.Trimesh:
    """Load one triangle mesh in millimetres, refusing files that are not a usable surface.

    ``expected_extent_mm`` bounds the largest bounding-box side of the object (used to detect
    the units and to reject absurd sizes). A mesh with holes gets a warning (signed distances
    then use winding numbers) unless ``require_watertight``.
    """
    path = Path(path)
    name = path.name
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    if path.suffix.lower() not in _SUPPORTED_SUFFIXES:
        raise MeshError(f"{name}: unsupported mesh format {path.suffix!r} (use STL, PLY or OBJ)")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except ImportError as exc:
        # Bytes that are neither binary STL nor text send trimesh to an optional text-encoding
        # detector; the missing module says nothing useful about the file.
        raise MeshError(f"{name}: not a readable mesh (corrupt, or not a {path.suffix} file)") from exc
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshError(f"{name}: cannot be read as a mesh ({exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{name}: contains no triangles")
    mesh = loaded
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{name}: has non-finite vertex coordinates")
    mesh.remove_unreferenced_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    if len(mesh.faces) < 4:
        raise MeshError(f"{name}: has only {len(mesh.faces)} usable triangles; not a surface")

    extent = float(np.max(mesh.extents))
    if units == "auto":
        scale = _detect_scale(extent, expected_extent_mm, name)
    elif units in UNIT_SCALE_TO_MM:
        scale = UNIT_SCALE_TO_MM[units]
        size = extent * scale
        if not expected_extent_mm[0] <= size <= expected_extent_mm[1]:
            raise MeshError(
                f"{name}: largest extent {size:.1f} mm (declared units {units}) is outside the "
                f"plausible {expected_extent_mm[0]:.0f}-{expected_extent_mm[1]:.0f} mm"
            )
    else:
        raise MeshError(f"{name}: unknown units {units!r} (use mm, cm, m or auto)")
    mesh.apply_scale(scale)

    if not mesh.is_watertight:
        message = f"{name}: mesh is not watertight ({_count_pieces(mesh)} pieces)"
        if require_watertight:
            raise MeshError(message)
        log.warning("%s; inside/outside is decided by winding numbers", message)
    elif mesh.volume < 0:
        mesh.invert()
    return mesh
