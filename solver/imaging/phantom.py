"""Simulated calibration phantom images: an acrylic plate carrying a grid of steel balls.

The plate is seen at many tilts through the same C-arm (same intrinsics, same intensifier
distortion), as a technician would hold it in the beam. Images may be inverted (a C-arm that
stores bone bright), may lose balls past the rim of the field, and may have a steel clamp
lying across part of the grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import trimesh

from ..camera import Camera
from ..geometry import Pose, rotation_about
from .distortion import Distortion
from .xray import Body, XRayParams, expose, render_bodies

__all__ = ["PhantomSpec", "simulate_phantom_images"]

_MU_STEEL = 0.9  # per mm, as XRayParams
_MU_ACRYLIC = 0.022


@dataclass(frozen=True)
class PhantomSpec:
    """Ball-grid plate: ``rows`` x ``cols`` balls ``pitch_mm`` apart (ball centres)."""

    rows: int = 5
    cols: int = 5
    pitch_mm: float = 25.0
    ball_diameter_mm: float = 3.0
    plate_thickness_mm: float = 6.0

    def __post_init__(self) -> None:
        if self.rows < 3 or self.cols < 3:
            raise ValueError(f"a {self.rows}x{self.cols} grid is too small to calibrate (>= 3x3)")
        if not 2.0 * self.ball_diameter_mm < self.pitch_mm <= 200.0:
            raise ValueError(f"pitch {self.pitch_mm} mm must exceed two ball diameters and be <= 200")
        if not 0.5 <= self.ball_diameter_mm <= 10.0:
            raise ValueError(f"ball diameter {self.ball_diameter_mm} mm is outside 0.5-10 mm")

    def points(self) -> np.ndarray:
        """Ball centres (rows*cols, 3) in the plate frame (mm), centred, z = 0."""
        j, i = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack([(j.ravel() - (self.cols - 1) / 2) * self.pitch_mm,
                                (i.ravel() - (self.rows - 1) / 2) * self.pitch_mm,
                                np.zeros(self.rows * self.cols)])

    def to_json(self) -> dict:
        return {"kind": "ball grid on acrylic plate", "rows": self.rows, "cols": self.cols,
                "pitch_mm": self.pitch_mm, "ball_diameter_mm": self.ball_diameter_mm}


def _bodies(spec: PhantomSpec, clamp: bool) -> list[Body]:
    ball = trimesh.creation.icosphere(subdivisions=2, radius=spec.ball_diameter_mm / 2.0)
    balls = trimesh.util.concatenate([ball.copy().apply_translation(p) for p in spec.points()])
    extent = max(spec.rows, spec.cols) * spec.pitch_mm + 20.0
    plate = trimesh.creation.box([extent, extent, spec.plate_thickness_mm])
    plate.apply_translation([0.0, 0.0, spec.plate_thickness_mm / 2.0 + spec.ball_diameter_mm / 2.0])
    bodies = [Body(balls.vertices, balls.faces, _MU_STEEL), Body(plate.vertices, plate.faces, _MU_ACRYLIC)]
    if clamp:
        bar = trimesh.creation.box([extent / 2.0, 10.0, 4.0])
        bar.apply_translation([extent / 4.0, spec.pitch_mm * (spec.rows - 1) / 2.0 - 2.0, -6.0])
        bodies.append(Body(bar.vertices, bar.faces, _MU_STEEL))
    return bodies


def simulate_phantom_images(camera: Camera, distortion: Distortion, spec: PhantomSpec, count: int,
                            rng: np.random.Generator, max_tilt_deg: float = 40.0,
                            inverted_fraction: float = 0.25, clamp_fraction: float = 0.2,
                            params: XRayParams = XRayParams()) -> list[np.ndarray]:
    """``count`` phantom frames (uint16) at random tilts (up to ``max_tilt_deg``) and
    positions, some inverted and some with a steel clamp across the grid."""
    images = []
    bodies = {clamp: _bodies(spec, clamp) for clamp in (False, True)}
    for _ in range(count):
        tilt_axis = rotation_about([0.0, 0.0, 1.0], rng.uniform(0, 2 * np.pi)) @ np.array([1.0, 0.0, 0.0])
        R = rotation_about(tilt_axis, np.radians(rng.uniform(5.0, max_tilt_deg))) @ \
            rotation_about([0.0, 0.0, 1.0], rng.uniform(-np.pi, np.pi))
        # Spread over the field so that balls also reach its rim, where distortion is largest.
        t = np.array([rng.normal(0.0, 20.0), rng.normal(0.0, 20.0), rng.uniform(560.0, 760.0)])
        clamp = bool(rng.random() < clamp_fraction)
        inverted = bool(rng.random() < inverted_fraction)
        line_integral = render_bodies([(b, Pose(R, t)) for b in bodies[clamp]], camera,
                                      np.zeros(2), camera.width, camera.height)
        # The grid sits well inside the frame: the ideal canvas is the frame itself, and the
        # pincushion only pulls content inwards.
        image = expose(line_integral, np.zeros(2), camera,
                       replace(params, invert=inverted), distortion, rng)
        images.append(image)
    return images
