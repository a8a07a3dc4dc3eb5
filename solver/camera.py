"""The X-ray camera: a pinhole at the X-ray source looking at the detector.

Frame ``cam`` (DESIGN.md section 3): origin at the X-ray source, +z from the source towards
the detector, x/y along image columns/rows. Pixel coordinates ``(u, v)`` have their origin at
the centre of the top-left pixel. Observed points are assumed already undistorted with the
C-arm's stored calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import row_norms

__all__ = ["Camera"]

# Points closer to the source than this (mm) are treated as behind the camera.
MIN_DEPTH_MM = 1.0


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels plus the image and field-of-view size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    fov_radius_px: float | None = None  # circular field of view of an image intensifier

    def __post_init__(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @staticmethod
    def from_geometry(
        source_to_detector_mm: float,
        field_mm: float,
        pixels: int,
        circular_field: bool = True,
    ) -> Camera:
        """Camera of a square detector ``field_mm`` wide with ``pixels`` per side."""
        focal = source_to_detector_mm * pixels / field_mm
        centre = (pixels - 1) / 2.0
        radius = pixels / 2.0 if circular_field else None
        return Camera(focal, focal, centre, centre, pixels, pixels, radius)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3)."""
        z = np.maximum(p_cam[:, 2], MIN_DEPTH_MM)
        return np.column_stack(
            [self.fx * p_cam[:, 0] / z + self.cx, self.fy * p_cam[:, 1] / z + self.cy]
        )

    def project_with_jacobian(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and their Jacobian (N, 2, 3) with respect to the camera-frame point."""
        x, y = p_cam[:, 0], p_cam[:, 1]
        z = np.maximum(p_cam[:, 2], MIN_DEPTH_MM)
        inv_z = 1.0 / z
        uv = np.column_stack([self.fx * x * inv_z + self.cx, self.fy * y * inv_z + self.cy])
        J = np.zeros((len(p_cam), 2, 3))
        J[:, 0, 0] = self.fx * inv_z
        J[:, 0, 2] = -self.fx * x * inv_z**2
        J[:, 1, 1] = self.fy * inv_z
        J[:, 1, 2] = -self.fy * y * inv_z**2
        return uv, J

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) in the camera frame of the rays through pixels (N, 2)."""
        d = np.column_stack(
            [(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy, np.ones(len(uv))]
        )
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def in_field(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image and its circular field of view."""
        inside = (
            (uv[:, 0] >= margin_px)
            & (uv[:, 1] >= margin_px)
            & (uv[:, 0] <= self.width - 1 - margin_px)
            & (uv[:, 1] <= self.height - 1 - margin_px)
        )
        if self.fov_radius_px is not None:
            centre = np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
            inside &= row_norms(uv - centre) <= self.fov_radius_px - margin_px
        return inside

    def to_json(self) -> dict:
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "fov_radius_px": self.fov_radius_px,
        }

    @staticmethod
    def from_json(d: dict) -> Camera:
        try:
            return Camera(
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                int(d["width"]),
                int(d["height"]),
                None if d.get("fov_radius_px") is None else float(d["fov_radius_px"]),
            )
        except KeyError as missing:
            raise ValueError(f"camera description lacks the field {missing}") from None
