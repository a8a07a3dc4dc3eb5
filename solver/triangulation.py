"""Closed-form starting pose of a pin from its contours in two or more views.

A pin is a thin straight rod: in each view its contour pixels lie along one image segment.
The two ends of that segment (the trocar tip and the pin's back end) are seen in every view,
so each end is triangulated from its rays, and the pin runs from one to the other. This is
well posed even when the back-projected planes of the views nearly coincide (pins running
front to back, seen from both sides of antero-posterior, lie close to both planes), where
intersecting the planes would amplify small view errors into degrees of axis error. It
replaces the planned pin pose (which may be tens of millimetres off) before the silhouette
optimisation, so the pins start next to where they are seen.
"""

from __future__ import annotations

from itertools import product

import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose

__all__ = ["PinSighting", "sighting_score", "triangulate_pin", "triangulate_rays"]

# Ends of the pixels' spread along the segment (percentiles), robust to stray contour pixels.
_END_PERCENTILES = (0.5, 99.5)
# Millimetres of meeting gap worth one millimetre of length discrepancy, when pairing ends.
_LENGTH_WEIGHT = 0.1


class PinSighting:
    """The contour pixels of one pin in one view, with that view's camera and pose.
    ``line_only``: the pixels say along which image line the pin lies, not where it ends
    (both pins one behind the other in one bar, whose ends are one pin's and the other's)."""

    def __init__(self, camera: Camera, T_cam_tibia: Pose, pixels: np.ndarray, line_only: bool = False):
        self.camera, self.T_cam_tibia, self.pixels = camera, T_cam_tibia, pixels
        self.line_only = line_only

    def source(self) -> np.ndarray:
        """X-ray source position in the tibia frame."""
        return self.T_cam_tibia.inverse().t

    def end_rays(self) -> np.ndarray:
        """Unit rays (2, 3), tibia frame, through the two ends of the pin's image segment."""
        centre = self.pixels.mean(axis=0)
        direction = np.linalg.svd(self.pixels - centre, full_matrices=False)[2][0]
        along = (self.pixels - centre) @ direction
        ends = centre + np.outer(np.percentile(along, _END_PERCENTILES), direction)
        return self.T_cam_tibia.inverse().rotate(self.camera.rays(ends))


def triangulate_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Point nearest to all rays (least squares) and its RMS distance to them, mm."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    across = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors across each ray
    point = np.linalg.solve(across.sum(axis=0), np.einsum("nij,nj->i", across, origins))
    gaps = np.einsum("nij,nj->ni", across, point - origins)
    return point, float(np.sqrt(np.mean(np.sum(gaps**2, axis=1))))


def _at_length(origin: np.ndarray, ray: np.ndarray, other: np.ndarray, length_mm: float) -> list[np.ndarray]:
    """The points of a ray ``length_mm`` from ``other`` (the nearest to it if none is)."""
    d = ray / np.linalg.norm(ray)
    b = float(d @ (origin - other))
    disc = b * b - (float(np.sum((origin - other) ** 2)) - length_mm**2)
    roots = [-b] if disc < 0 else [-b - np.sqrt(disc), -b + np.sqrt(disc)]
    return [origin + t * d for t in roots]


def _best_ends(sightings: list[PinSighting], length_mm: float | None
               ) -> tuple[float, np.ndarray, np.ndarray]:
    """The pin's two ends triangulated from the sightings' segment ends, and the pairing's
    score (mm): how badly the rays meet, plus how far the pin is from the model's length."""
    named = [s for s in sightings if not s.line_only]
    lines = [s for s in sightings if s.line_only]
    sources = [s.source() for s in named]
    end_rays = [s.end_rays() for s in named]
    line_rays = [s.end_rays() for s in lines]
    normals = [np.cross(*rays) / np.linalg.norm(np.cross(*rays)) for rays in line_rays]
    # Which end of each view's segment is which is not known. A pin running front to back
    # lies close to the epipolar plane of views on both sides of AP, so the wrong pairing
    # still nearly meets (a fraction of a millimetre): the pairing is chosen by how well its
    # rays meet and, above all, by how close the triangulated pin is to the model's length.
    # A bar of both pins in line (``line_only``) ends in one end of each: one of its ends
    # is one of this pin's, and its other end, hidden in the bar, lies on its ray from the
    # other views the pin's length away, in the plane through the bar (of the two such
    # points, the nearer it: that plane nearly holds the others' rays, so it cannot place
    # the end by itself).
    best = None
    for flips in product((0, 1), repeat=len(named) - 1):
        order = (0,) + flips
        for held in product(range(4), repeat=len(lines)):  # (bar end, pin end) per bar
            rays: list[list[tuple[np.ndarray, np.ndarray]]] = [[], []]
            for source, r, o in zip(sources, end_rays, order):
                for end in (0, 1):
                    rays[end].append((source, r[end ^ o]))
            for s, r, (bar_end, end) in zip(lines, line_rays, (divmod(h, 2) for h in held)):
                rays[end].append((s.source(), r[bar_end]))
            for candidate in _ends(rays, length_mm, [s.source() for s in lines], normals):
                if best is None or candidate[0] < best[0]:
                    best = candidate
    assert best is not None
    return best


def _ends(rays: list[list[tuple[np.ndarray, np.ndarray]]], length_mm: float | None,
          plane_points: list[np.ndarray], normals: list[np.ndarray]
          ) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Candidate ends (score, end 0, end 1) from each end's rays (origin, direction)."""
    met = [triangulate_rays(np.array([o for o, _ in r]), np.array([d for _, d in r])) if len(r) >= 2 else None
           for r in rays]
    if met[0] is not None and met[1] is not None:
        score = met[0][1] + met[1][1]
        if length_mm is not None:
            score += _LENGTH_WEIGHT * abs(float(np.linalg.norm(met[1][0] - met[0][0])) - length_mm)
        return [(score, met[0][0], met[1][0])]
    known = 0 if met[0] is not None else 1
    found = met[known]
    if found is None or length_mm is None or not rays[1 - known]:
        return []
    origin, ray = rays[1 - known][0]
    candidates = []
    for point in _at_length(origin, ray, found[0], length_mm):
        off = sum(abs(float((point - p) @ n)) for p, n in zip(plane_points, normals))
        ends = (found[0], point) if known == 0 else (point, found[0])
        candidates.append((found[1] + off, *ends))
    return candidates


def _enough(sightings: list[PinSighting]) -> list[PinSighting] | None:
    """The sightings with pixels enough, if two or more and one shows the pin's ends."""
    sightings = [s for s in sightings if len(s.pixels) >= 3]
    return sightings if len(sightings) >= 2 and not all(s.line_only for s in sightings) else None


def sighting_score(sightings: list[PinSighting], length_mm: float | None = None) -> float:
    """How well the sightings fit one pin (mm, lower is better; inf when under two views)."""
    usable = _enough(sightings)
    return _best_ends(usable, length_mm)[0] if usable is not None else float("inf")


def triangulate_pin(sightings: list[PinSighting], prior: Pose,
                    length_mm: float | None = None) -> Pose | None:
    """Pin pose (+z along the axis from the tip, tip at the origin) seen in ``sightings``;
    ``prior`` (the current or planned pose) decides which end is the tip and the roll;
    ``length_mm``, the pin model's length, helps to pair the segment ends across views.
    None if the pin is seen in fewer than two views."""
    usable = _enough(sightings)
    if usable is None:
        return None
    _, a, b = _best_ends(usable, length_mm)
    axis = b - a
    if np.linalg.norm(axis) < 1e-6:
        return None
    axis /= np.linalg.norm(axis)
    tip = a
    if np.dot(axis, prior.R[:, 2]) < 0:
        axis, tip = -axis, b

    x = prior.R[:, 0] - np.dot(prior.R[:, 0], axis) * axis
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return Pose(np.column_stack([x, np.cross(axis, x), axis]), tip)
