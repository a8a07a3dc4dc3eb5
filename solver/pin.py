"""The parametric trocar pin that fixes a tibial cutting block.

Pin frame (README.md, Conventions): the pin axis is +z, the trocar tip at the origin, the shaft
running to ``z = length``. The tip is the classic three-facet trocar: three planes through the
tip point, 120 degrees apart, each rising with slope ``tip_length / radius`` towards the
shaft wall, so the ridges between facets are sharp and the tip is ``tip_length`` long.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamtka.solver.surface import Surface

__all__ = ["PinSpec", "build_pin"]

# Angular samples around the shaft; a multiple of 6 so the three ridges are sampled exactly.
_AROUND = 48
_TIP_RINGS = 6


@dataclass(frozen=True)
class PinSpec:
    """Dimensions of a trocar pin in millimetres (defaults: a common 3.2 mm TKA pin)."""

    diameter_mm: float = 3.2
    length_mm: float = 90.0
    tip_length_mm: float = 5.0

    def __post_init__(self) -> None:
        if not 0.5 <= self.diameter_mm <= 10.0:
            raise ValueError(f"pin diameter {self.diameter_mm} mm is not a plausible trocar pin")
        if not 20.0 <= self.length_mm <= 300.0:
            raise ValueError(f"pin length {self.length_mm} mm is outside 20-300 mm")
        if not 0.0 < self.tip_length_mm < self.length_mm / 2:
            raise ValueError(f"pin tip length {self.tip_length_mm} mm is implausible")


def build_pin(spec: PinSpec = PinSpec()) -> Surface:
    """Watertight triangle mesh of the pin in the pin frame (mm): distinct vertices and
    outward-wound faces by construction, as trimesh's processing would leave them."""
    radius = spec.diameter_mm / 2.0
    theta = np.arange(_AROUND) * (2.0 * np.pi / _AROUND)
    facet_dirs = np.array([0.0, 2.0 * np.pi / 3.0, 4.0 * np.pi / 3.0])
    # Height of the tip surface above the point, per unit radius: the highest facet wins.
    rise = (spec.tip_length_mm / radius) * np.max(np.cos(theta[:, None] - facet_dirs[None]), axis=1)

    ring_radii = radius * np.arange(1, _TIP_RINGS + 1) / _TIP_RINGS
    tip_rings = np.stack(
        [
            np.outer(ring_radii, np.cos(theta)),
            np.outer(ring_radii, np.sin(theta)),
            np.outer(ring_radii, rise),
        ],
        axis=-1,
    ).reshape(-1, 3)
    top_ring = np.column_stack(
        [radius * np.cos(theta), radius * np.sin(theta), np.full(_AROUND, spec.length_mm)]
    )
    apex = np.zeros((1, 3))
    top_centre = np.array([[0.0, 0.0, spec.length_mm]])
    vertices = np.vstack([apex, tip_rings, top_ring, top_centre])

    def ring(index: int) -> np.ndarray:
        return 1 + index * _AROUND + np.arange(_AROUND)

    nxt = np.roll(np.arange(_AROUND), -1)
    faces = [np.column_stack([np.zeros(_AROUND, int), ring(0)[nxt], ring(0)])]
    # Rings 0.._TIP_RINGS-1 form the tip, ring _TIP_RINGS is the top of the shaft.
    for r in range(_TIP_RINGS):
        a, b = ring(r), ring(r + 1)
        faces.append(np.column_stack([a, b[nxt], b]))
        faces.append(np.column_stack([a, a[nxt], b[nxt]]))
    centre = len(vertices) - 1
    last = ring(_TIP_RINGS)
    faces.append(np.column_stack([np.full(_AROUND, centre), last, last[nxt]]))
    return Surface(vertices, np.vstack(faces).astype(np.int64))
