"""The lit field of an X-ray frame and its attenuation image, shared by contours and calibration.

An image intensifier images a circle; the frame's corners carry only the no-signal level.
Which side is brighter tells the polarity (MONOCHROME2 with bone and metal dark, or an
inverted image), and ``-log(signal)`` turns the frame into attenuation, in which bodies add.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["FieldError", "field_of_view", "attenuation", "fill_holes"]


class FieldError(ValueError):
    """A frame whose field of view cannot be found, with the reason."""


def _fit_circle(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Circle through most of the points (RANSAC over triplets), refined by least squares.

    Objects crossing the rim of the field (a pin sticking out) dent its boundary, so the
    consensus circle, not a plain fit, is the field.
    """
    triplets = points[rng.integers(0, len(points), (300, 3))]
    a, b, c = triplets[:, 0], triplets[:, 1], triplets[:, 2]
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    ok = np.abs(d) > 1e-6
    a, b, c, d = a[ok], b[ok], c[ok], d[ok]
    sa, sb, sc = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    centres = np.column_stack([
        (sa * (b[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - b[:, 1])) / d,
        (sa * (c[:, 0] - b[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (b[:, 0] - a[:, 0])) / d])
    radii = np.linalg.norm(a - centres, axis=1)
    # Score candidates on a subsample of the boundary to keep this vectorised and small.
    sample = points[:: max(1, len(points) // 400)]
    residual = np.abs(np.linalg.norm(sample[None] - centres[:, None], axis=2) - radii[:, None])
    best = int(np.argmax((residual < 1.5).sum(axis=1)))
    keep = np.abs(np.linalg.norm(points - centres[best], axis=1) - radii[best]) < 1.5
    p = points[keep]
    M = np.column_stack([2 * p, np.ones(len(p))])
    sol = np.linalg.lstsq(M, (p**2).sum(axis=1), rcond=None)[0]
    return sol[:2], float(np.sqrt(sol[2] + sol[:2] @ sol[:2]))


def field_of_view(image: np.ndarray, polarity: str) -> tuple[np.ndarray, float | None, float, int]:
    """Centre, radius (None: the whole frame is imaged), no-signal level and sign of signal."""
    h, w = image.shape
    c = max(4, min(h, w) // 64)
    corners = np.concatenate([image[:c, :c].ravel(), image[:c, -c:].ravel(),
                              image[-c:, :c].ravel(), image[-c:, -c:].ravel()])
    outside = float(np.median(corners))
    inside = float(np.median(image[h // 4: 3 * h // 4, w // 4: 3 * w // 4]))
    sign = {"dark": 1, "bright": -1}.get(polarity, 1 if inside >= outside else -1)
    if abs(inside - outside) < 8.0 * (np.std(corners) + 1.0):
        # Corners carry signal: a flat-panel or cropped frame without a circular field.
        level = float(np.min(image)) if sign > 0 else float(np.max(image))
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0]), None, level, sign
    lit = (sign * (image.astype(np.float32) - outside) > 0.5 * abs(inside - outside)).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(lit, connectivity=8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = fill_holes(labels == largest).astype(np.uint8)
    boundary = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    points = np.vstack([b.reshape(-1, 2) for b in boundary]).astype(float)
    # Drop the frame's border: the field may be cut by the frame.
    points = points[(points[:, 0] > 1) & (points[:, 1] > 1) & (points[:, 0] < w - 2) & (points[:, 1] < h - 2)]
    if len(points) < 50:
        raise FieldError("the circular field of view could not be found")
    centre, radius = _fit_circle(points, np.random.default_rng(0))
    return centre, radius, outside, sign


def attenuation(image: np.ndarray, outside: float, sign: int) -> np.ndarray:
    signal = sign * (image.astype(np.float32) - outside)
    return -np.log(np.maximum(signal, 1.0))


def fill_holes(mask: np.ndarray, max_area: int | None = None) -> np.ndarray:
    """The mask with its enclosed holes (smaller than ``max_area``, if given) filled."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=4)
    h, w = mask.shape
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    fill = (x > 0) & (y > 0) & (x + stats[:, cv2.CC_STAT_WIDTH] < w) & (y + stats[:, cv2.CC_STAT_HEIGHT] < h)
    if max_area is not None:
        fill &= stats[:, cv2.CC_STAT_AREA] < max_area
    return mask.astype(bool) | fill[labels]
