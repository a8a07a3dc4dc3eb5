"""Geometric distortion of an X-ray image intensifier: pincushion plus S-shaped twist.

An image intensifier projects the X-ray image onto a curved input phosphor and carries it as
an electron image to the output phosphor. The curved input screen magnifies more towards the
rim (pincushion, radial distortion), and the Earth's or the room's magnetic field deflects
the electrons by an angle that grows with their distance from the tube axis (S-distortion:
straight lines come out S-shaped). Both are symmetric about the tube axis, so the model is
written in polar coordinates about a distortion centre (the centre of the circular field of
view, which an image shows directly):

    rho = r / R                                    (R: reference radius, the field radius)
    r_distorted     = r * (1 + k1 rho^2 + k2 rho^4)
    theta_distorted = theta + t1 rho^2 + t2 rho^4  (radians)

``k1, k2`` (dimensionless, > 0 for pincushion) are typically 0.02-0.10 for a 23 cm
intensifier; ``t1, t2`` (radians of twist at the rim) are typically a few milliradians and
depend on how the C-arm is oriented in the magnetic field. A constant rotation or shift of the
whole image is not distortion: it belongs to the camera pose and principal point.

Coordinates are pixels with the origin at the centre of the top-left pixel. ``distort`` maps
ideal (pinhole) pixel positions to where the intensifier shows them; ``undistort`` is its
exact inverse (a monotone 1-D radial equation solved by Newton's method).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

__all__ = ["Distortion", "MODEL_NAME"]

MODEL_NAME = "image-intensifier/1"
_NEWTON_ITERATIONS = 12


@dataclass(frozen=True)
class Distortion:
    """Image-intensifier distortion about ``(centre_u, centre_v)`` with reference radius ``radius``."""

    centre_u: float
    centre_v: float
    radius: float
    k1: float = 0.0
    k2: float = 0.0
    t1: float = 0.0
    t2: float = 0.0

    def __post_init__(self) -> None:
        values = (self.centre_u, self.centre_v, self.radius, self.k1, self.k2, self.t1, self.t2)
        if not all(np.isfinite(values)):
            raise ValueError("distortion parameters must be finite")
        if self.radius <= 0:
            raise ValueError(f"distortion reference radius must be positive, got {self.radius}")
        # The radial map must stay monotone up to 1.5 R, else it has no inverse there.
        rho = np.linspace(0.0, 1.5, 61)
        if np.any(1.0 + 3.0 * self.k1 * rho**2 + 5.0 * self.k2 * rho**4 <= 0.05):
            raise ValueError(f"radial distortion k1={self.k1}, k2={self.k2} folds the image")

    @staticmethod
    def none(width: int, height: int) -> Distortion:
        """The identity (a flat-panel detector, or an already corrected image)."""
        return Distortion((width - 1) / 2.0, (height - 1) / 2.0, max(width, height) / 2.0)

    @property
    def is_identity(self) -> bool:
        return self.k1 == self.k2 == self.t1 == self.t2 == 0.0

    @property
    def params(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.t1, self.t2])

    def with_params(self, params: np.ndarray) -> Distortion:
        k1, k2, t1, t2 = (float(p) for p in params)
        return Distortion(self.centre_u, self.centre_v, self.radius, k1, k2, t1, t2)

    def _polar(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.asarray(uv, float).reshape(-1, 2) - [self.centre_u, self.centre_v]
        return np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])

    def _cartesian(self, r: np.ndarray, theta: np.ndarray) -> np.ndarray:
        return np.column_stack([self.centre_u + r * np.cos(theta), self.centre_v + r * np.sin(theta)])

    def distort(self, uv: np.ndarray) -> np.ndarray:
        """Observed (distorted) pixel positions (N, 2) of ideal pinhole positions (N, 2)."""
        return self.distort_with(self.params, uv)

    def distort_with(self, params: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """:meth:`distort` with other parameters (k1, k2, t1, t2), not checked: a fit's trial
        step may fold the map, and must be seen to fit badly rather than fail."""
        k1, k2, t1, t2 = params
        r, theta = self._polar(uv)
        rho2 = (r / self.radius) ** 2
        return self._cartesian(r * (1.0 + k1 * rho2 + k2 * rho2**2), theta + t1 * rho2 + t2 * rho2**2)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pinhole positions (N, 2) of observed (distorted) pixel positions (N, 2)."""
        r_d, theta_d = self._polar(uv)
        if self.is_identity:
            return np.asarray(uv, float).reshape(-1, 2).copy()
        R = self.radius
        r = r_d.copy()
        for _ in range(_NEWTON_ITERATIONS):
            rho2 = (r / R) ** 2
            f = r * (1.0 + self.k1 * rho2 + self.k2 * rho2**2) - r_d
            df = 1.0 + 3.0 * self.k1 * rho2 + 5.0 * self.k2 * rho2**2
            r = np.maximum(r - f / df, 0.0)
        rho2 = (r / R) ** 2
        return self._cartesian(r, theta_d - self.t1 * rho2 - self.t2 * rho2**2)

    def warp(self, ideal: np.ndarray, width: int, height: int, origin: tuple[float, float] = (0.0, 0.0),
             border_value: float = 0.0) -> np.ndarray:
        """The distorted (height, width) image of an ideal image.

        ``ideal`` may cover a larger canvas whose pixel (0, 0) sits at ideal position
        ``origin``, so content that distortion pulls in from beyond the frame is available.
        """
        map_u, map_v = _source_maps(self, width, height)
        return cv2.remap(ideal, map_u - np.float32(origin[0]), map_v - np.float32(origin[1]), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=border_value)

    def to_json(self) -> dict:
        return {"model": MODEL_NAME, "centre_px": [self.centre_u, self.centre_v],
                "radius_px": self.radius, "k1": self.k1, "k2": self.k2, "t1_rad": self.t1,
                "t2_rad": self.t2}

    @staticmethod
    def from_json(doc: dict) -> Distortion:
        if doc.get("model") != MODEL_NAME:
            raise ValueError(f"distortion model {doc.get('model')!r} is not {MODEL_NAME!r}")
        try:
            centre = [float(x) for x in doc["centre_px"]]
            return Distortion(centre[0], centre[1], float(doc["radius_px"]), float(doc["k1"]),
                              float(doc["k2"]), float(doc["t1_rad"]), float(doc["t2_rad"]))
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"distortion description is incomplete or malformed ({exc})") from None


@lru_cache(maxsize=4)
def _source_maps(distortion: Distortion, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ideal position of every distorted pixel (float32 maps); fixed per C-arm, so cached."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    source = distortion.undistort(np.column_stack([u.ravel(), v.ravel()]))
    return (source[:, 0].reshape(height, width).astype(np.float32),
            source[:, 1].reshape(height, width).astype(np.float32))
