"""The X-ray camera: a pinhole at the X-ray source looking at the detector.

Frame ``cam`` (README.md, Conventions): origin at the X-ray source, +z from the source towards
the detector, x/y along image columns/rows. Pixel coordinates ``(u, v)`` have their origin at
the centre of the top-left pixel. Observed points are assumed already undistorted with the
C-arm's stored calibration.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np

from slamtka.solver.kernels import in_field, pinhole

__all__ = ["Camera"]

# Points closer to the source than this (mm) are treated as behind the camera.
MIN_DEPTH_MM = 1.0

# Plausible image sides in pixels: a larger value is a typo that would exhaust memory in the
# full-image distance maps, a smaller one cannot hold a contour.
MIN_IMAGE_SIDE_PX = 16
MAX_IMAGE_SIDE_PX = 16384


def _image_side(name: str, value) -> int:
    """``value`` as a whole number of pixels (a float is accepted only if integral, so a
    fractional size is refused rather than silently truncated)."""
    if isinstance(value, bool):
        raise ValueError(f"camera {name} must be a whole number of pixels, got {value!r}")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    try:
        side = operator.index(value)
    except TypeError:
        raise ValueError(f"camera {name} must be a whole number of pixels, got {value!r}") from None
    if not MIN_IMAGE_SIDE_PX <= side <= MAX_IMAGE_SIDE_PX:
        raise ValueError(f"camera {name} {side} px is outside {MIN_IMAGE_SIDE_PX}..{MAX_IMAGE_SIDE_PX}")
    return side


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
        # NaN compares false with everything, so each test is written to fail on it.
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be finite and positive, got fx={self.fx}, fy={self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError(f"principal point must be finite, got cx={self.cx}, cy={self.cy}")
        _image_side("width", self.width)
        _image_side("height", self.height)
        if self.fov_radius_px is not None and not (math.isfinite(self.fov_radius_px)
                                                   and self.fov_radius_px > 0):
            raise ValueError(f"fov_radius_px must be finite and positive, got {self.fov_radius_px}")

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

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) as floats: one compiled projection kernel for every camera."""
        return float(self.fx), float(self.fy), float(self.cx), float(self.cy)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3)."""
        return pinhole(np.asarray(p_cam, float), *self.intrinsics, MIN_DEPTH_MM, False)[0]

    def project_with_jacobian(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and their Jacobian (N, 2, 3) with respect to the camera-frame point."""
        return pinhole(np.asarray(p_cam, float), *self.intrinsics, MIN_DEPTH_MM, True)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) in the camera frame of the rays through pixels (N, 2)."""
        d = np.column_stack(
            [(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy, np.ones(len(uv))]
        )
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    @property
    def fov_radius(self) -> float:
        """The circular field of view's radius in pixels (inf: none)."""
        return math.inf if self.fov_radius_px is None else float(self.fov_radius_px)

    def in_field(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image and its circular field of view."""
        return in_field(np.asarray(uv, float).reshape(-1, 2), self.width, self.height, float(margin_px),
                        self.fov_radius)

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
        if not isinstance(d, dict):
            raise ValueError(f"camera description must be an object, not {type(d).__name__}")
        try:
            return Camera(
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                _image_side("width", d["width"]),
                _image_side("height", d["height"]),
                None if d.get("fov_radius_px") is None else float(d["fov_radius_px"]),
            )
        except KeyError as missing:
            raise ValueError(f"camera description lacks the field {missing}") from None
        except TypeError as exc:
            raise ValueError(f"camera description has a field of the wrong type ({exc})") from None
