"""Contour observations of one X-ray view and their distance maps.

Each view carries the calibrated camera, the pixel positions (undistorted) of the observed
outer edges of the bone (tibia with fibula) and of each pin, and the camera pose guess taken
from the C-arm encoders. The model-projection term needs, for any pixel, the distance to the
nearest observed edge of a label: that is a distance transform of the rasterised contour,
queried with bilinear interpolation and its exact gradient.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .camera import Camera

__all__ = ["LABELS", "PIN_LABELS", "DistanceMap", "ViewObservation"]

LABELS = ("bone", "pin1", "pin2")
PIN_LABELS = ("pin1", "pin2")


@dataclass(frozen=True)
class DistanceMap:
    """Distance in pixels from every pixel to the nearest observed contour point."""

    values: np.ndarray  # (H, W) float32

    @staticmethod
    def from_points(points_px: np.ndarray, width: int, height: int) -> DistanceMap:
        image = np.full((height, width), 255, np.uint8)
        pix = np.round(points_px).astype(int)
        ok = (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
        image[pix[ok, 1], pix[ok, 0]] = 0
        return DistanceMap(cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))

    def query(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (N,) and gradients (N, 2) in d/du, d/dv at pixel positions (N, 2).

        Beyond the image border the distance keeps growing linearly so projections that fall
        outside are pulled back in.
        """
        h, w = self.values.shape
        clamped = np.column_stack([np.clip(uv[:, 0], 0, w - 1 - 1e-9),
                                   np.clip(uv[:, 1], 0, h - 1 - 1e-9)])
        i0 = np.floor(clamped).astype(np.int64)
        f = clamped - i0
        v = self.values
        v00 = v[i0[:, 1], i0[:, 0]]
        v10 = v[i0[:, 1], i0[:, 0] + 1]
        v01 = v[i0[:, 1] + 1, i0[:, 0]]
        v11 = v[i0[:, 1] + 1, i0[:, 0] + 1]
        fu, fv = f[:, 0], f[:, 1]
        top = v00 * (1 - fu) + v10 * fu
        bottom = v01 * (1 - fu) + v11 * fu
        value = top * (1 - fv) + bottom * fv
        grad = np.column_stack([(v10 - v00) * (1 - fv) + (v11 - v01) * fv, bottom - top])
        outside = uv - clamped
        dist_out = np.linalg.norm(outside, axis=1)
        far = dist_out > 0
        if np.any(far):
            grad[outside != 0] = 0.0
            value = value + dist_out
            grad[far] += outside[far] / dist_out[far, None]
        return value.astype(float), grad.astype(float)


@dataclass
class ViewObservation:
    """One X-ray view: calibrated camera, labelled contour pixels, identity."""

    view_id: str
    camera: Camera
    contours: dict[str, np.ndarray]  # label -> (N, 2) undistorted pixel positions
    _distance_maps: dict[str, DistanceMap] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        unknown = set(self.contours) - set(LABELS)
        if unknown:
            raise ValueError(f"view {self.view_id}: unknown contour labels {sorted(unknown)}")
        for label in LABELS:
            pts = np.asarray(self.contours.get(label, np.zeros((0, 2))), dtype=float)
            if pts.size and (pts.ndim != 2 or pts.shape[1] != 2):
                raise ValueError(f"view {self.view_id}: {label} contour must be a list of (u, v)")
            pts = pts.reshape(-1, 2)
            if not np.all(np.isfinite(pts)):
                raise ValueError(f"view {self.view_id}: {label} contour has non-finite points")
            self.contours[label] = pts

    def distance_map(self, label: str) -> DistanceMap:
        if label not in self._distance_maps:
            self._distance_maps[label] = DistanceMap.from_points(
                self.contours[label], self.camera.width, self.camera.height
            )
        return self._distance_maps[label]
