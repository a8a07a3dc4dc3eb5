"""Pins through a tibial cutting block, in the tibia's anatomical frame (README.md, Conventions).

The block sits on the anteromedial tibia and guides two parallel pins, drilled posteriorly
in the resection plane. The simulator places them at random angles and offsets, the
service at the plan's target as the solver's starting guess; both build them here.
"""

from __future__ import annotations

import numpy as np

from slamtka.solver.geometry import Pose, rotation_about
from slamtka.solver.sdf import SignedDistanceField

__all__ = ["block_axes", "bone_entry_mm", "pin_pose"]


def block_axes(normal: np.ndarray, turn_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit directions of the pins (``posterior``: drilling) and of their spacing
    (``across``, towards +x so that offsets are signed like x), for a resection plane of
    unit ``normal``; the block may be turned by ``turn_rad`` about the normal."""
    posterior = np.array([0.0, -1.0, 0.0])
    posterior -= np.dot(posterior, normal) * normal
    posterior = rotation_about(normal, turn_rad) @ posterior
    posterior /= np.linalg.norm(posterior)
    across = np.cross(normal, posterior)
    across *= np.sign(across[0])
    return posterior, across


def bone_entry_mm(sdf: SignedDistanceField, T_tibia_anat: Pose, start: np.ndarray,
                  direction: np.ndarray, step_mm: float, length_mm: float = 300.0) -> float | None:
    """Distance from ``start`` (anatomical frame) along ``direction`` to where the line
    enters the bone, to ``step_mm``; None when it misses the bone within ``length_mm``."""
    t = np.arange(0.0, length_mm, step_mm)
    inside = np.nonzero(sdf.query(T_tibia_anat.apply(start + t[:, None] * direction))[0] < 0)[0]
    return float(t[inside[0]]) if len(inside) else None


def pin_pose(T_tibia_anat: Pose, tip: np.ndarray, posterior: np.ndarray) -> Pose:
    """``T_tibia_pin`` of a pin with its tip at ``tip`` (anatomical frame), drilled along
    ``posterior``: its +z runs from the tip back out towards the block, its +x is level."""
    z_axis = -posterior
    x_axis = np.cross([0.0, 0.0, 1.0], z_axis)
    x_axis /= np.linalg.norm(x_axis)
    return T_tibia_anat @ Pose(np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis]), tip)
