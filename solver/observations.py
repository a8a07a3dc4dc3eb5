"""Contour observations of one X-ray view and their distance maps.

Each view carries the calibrated camera and the pixel positions (undistorted) of the observed
outer edges of the bone (tibia with fibula) and of each pin; the pose guesses from the C-arm
encoders travel separately (``solver.slam.InitialGuess``). The model-projection term needs, for any pixel, the distance to the
nearest observed edge of a label: that is a distance transform of the rasterised contour,
queried with bilinear interpolation and its exact gradient.
"""

from __future__ import annotations

import base64
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.kernels import bilinear

__all__ = ["LABELS", "PIN_LABELS", "DistanceMap", "EdgeSearch", "ViewObservation", "VisibleRegion"]

LABELS = ("bone", "pin1", "pin2")
PIN_LABELS = ("pin1", "pin2")


# A distance map is computed only this far around its contour (beyond, the query's linear
# growth is an upper bound, which is all a far point needs to be pulled back): a pin's map
# then costs a tenth of a full-image transform, the bone's about half.
MAP_MARGIN_PX = 128


@dataclass(frozen=True)
class DistanceMap:
    """Distance in pixels to the nearest observed contour point, over a window of the image.

    ``values[i, j]`` is the distance at pixel ``(origin[0] + j, origin[1] + i)``; the window
    is the whole image unless the map was built with a margin."""

    values: np.ndarray  # (h, w) float32
    origin: tuple[int, int] = (0, 0)  # (u, v) of values[0, 0]
    image_size: tuple[int, int] | None = None  # (width, height) of the whole image
    margin_px: int | None = None  # how far around the contour the window reaches (None: all)

    @staticmethod
    def from_points(points_px: np.ndarray, width: int, height: int,
                    margin_px: int | None = None) -> DistanceMap:
        """The map over the whole ``width`` x ``height`` image, or with ``margin_px`` over the
        points' bounding box grown by that margin (clipped to the image)."""
        pix = np.round(points_px).astype(int)
        ok = (pix[:, 0] >= 0) & (pix[:, 0] < width) & (pix[:, 1] >= 0) & (pix[:, 1] < height)
        pix = pix[ok]
        lo, hi = np.zeros(2, int), np.array([width, height])
        if margin_px is not None and len(pix):
            lo = np.maximum(pix.min(axis=0) - margin_px, 0)
            hi = np.minimum(pix.max(axis=0) + margin_px + 1, [width, height])
        image = np.full((hi[1] - lo[1], hi[0] - lo[0]), 255, np.uint8)
        image[pix[:, 1] - lo[1], pix[:, 0] - lo[0]] = 0
        return DistanceMap(cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                           (int(lo[0]), int(lo[1])), (width, height), margin_px)

    def truncated(self, limit_px: float) -> np.ndarray:
        """The whole image's distances capped at ``limit_px`` (H, W), for the global searches
        that slide over all of it. Beyond the window every pixel is at least the margin away
        from the contour, so this is exact when the margin is at least the limit."""
        h, w = self.values.shape
        width, height = self.image_size or (w, h)
        if self.margin_px is not None and limit_px > self.margin_px:
            raise ValueError(f"a windowed distance map cannot be truncated at {limit_px} px "
                             f"(its margin is {self.margin_px} px)")
        field = np.full((height, width), limit_px, np.float32)
        u, v = self.origin
        field[v:v + h, u:u + w] = np.minimum(self.values, limit_px)
        return field

    @property
    def origin_uv(self) -> np.ndarray:
        """``origin`` as the float array (2,) the compiled lookups take."""
        return np.asarray(self.origin, float)

    def query(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (N,) and gradients (N, 2) in d/du, d/dv at pixel positions (N, 2).

        Beyond the window the distance keeps growing linearly so projections that fall
        outside are pulled back in.
        """
        return bilinear(self.values, self.origin_uv, np.asarray(uv, float))


@dataclass(frozen=True)
class VisibleRegion:
    """Where in a view the bone's edge could have been seen had it been there: inside the
    exposed field, clear of metal and collimator blades, burned-in text and the pins'
    shadows. Outside it a model's outline has no contour to lie on, so it is neither
    charged for lying off the contour nor counted by the gates (docs/solver.md, "What the
    frame hides").

    ``cells[i, j]`` covers the undistorted pixels ``cell_px * (j, i)`` to
    ``cell_px * (j + 1, i + 1)``; beyond the grid nothing is visible."""

    cells: np.ndarray  # (h, w) bool
    cell_px: int

    def __post_init__(self) -> None:
        if self.cells.ndim != 2 or self.cells.dtype != bool or self.cell_px < 1:
            raise ValueError("a visible region is a 2-D boolean grid of cells of at least 1 px")

    @staticmethod
    def from_raw(raw_cells: np.ndarray, cell_px: int, size: tuple[int, int],
                 distort: Callable[[np.ndarray], np.ndarray]) -> VisibleRegion:
        """The region over undistorted pixels of an image of ``size`` (width, height), from
        its cells over raw (distorted) pixels: each undistorted cell takes the raw cell
        its centre is imaged at (``distort``: undistorted to raw pixels)."""
        h, w = -(-size[1] // cell_px), -(-size[0] // cell_px)
        j, i = np.meshgrid(np.arange(w), np.arange(h))
        centres = cell_px * (np.column_stack([j.ravel(), i.ravel()]) + 0.5)
        region = VisibleRegion(np.asarray(raw_cells, bool), cell_px)
        return VisibleRegion(region.contains(distort(centres)).reshape(h, w), cell_px)

    def to_json(self) -> dict:
        """The grid as JSON: its shape, and its cells as packed bits in base64."""
        bits = base64.b64encode(np.packbits(self.cells.ravel()).tobytes()).decode("ascii")
        return {"cell_px": self.cell_px, "shape": list(self.cells.shape), "cells": bits}

    @staticmethod
    def from_json(doc: dict) -> VisibleRegion:
        h, w = (int(n) for n in doc["shape"])
        bits = np.frombuffer(base64.b64decode(doc["cells"]), np.uint8)
        if h < 1 or w < 1 or len(bits) * 8 < h * w:
            raise ValueError(f"a visible region of shape {h} x {w} needs {h * w} bits")
        return VisibleRegion(np.unpackbits(bits)[:h * w].reshape(h, w).astype(bool), int(doc["cell_px"]))

    def contains(self, uv: np.ndarray) -> np.ndarray:
        """Which pixel positions (N, 2) lie in the region (N,)."""
        cell = np.floor(np.asarray(uv, float) / self.cell_px).astype(np.int64)
        h, w = self.cells.shape
        inside = (cell[:, 0] >= 0) & (cell[:, 1] >= 0) & (cell[:, 0] < w) & (cell[:, 1] < h)
        found = np.zeros(len(cell), bool)
        found[inside] = self.cells[cell[inside, 1], cell[inside, 0]]
        return found


class EdgeSearch(Protocol):
    """A frame's bone edges near an expected outline (:class:`slamtka.solver.imaging.edges.
    BoneEdgeSearch`): given the bone model's projection as a mask over the undistorted
    image, the edge pixels (N, 2, undistorted) found within ``reach_px`` of its outline,
    and the share of its visible outline that found one."""

    def __call__(self, footprint: np.ndarray, reach_px: float) -> tuple[np.ndarray, float]: ...

    def to_json(self) -> dict: ...


@dataclass
class ViewObservation:
    """One X-ray view: calibrated camera, labelled contour pixels, identity."""

    view_id: str
    camera: Camera
    contours: dict[str, np.ndarray]  # label -> (N, 2) undistorted pixel positions
    # Why a label has no contour in this view, when the extraction could say ("hidden by
    # metal"): named in the refusal.
    notes: dict[str, str] = field(default_factory=dict)
    # Where the bone's edge could be seen (None: wherever the camera's field reaches).
    bone_visible: VisibleRegion | None = None
    # Searches the frame again for the bone's edges where the model says they are (None:
    # only the contours given, e.g. drawn by hand).
    bone_edge_search: EdgeSearch | None = None
    # The pin contours are outlines of the pins' shadows in a radiograph, where steel hides
    # what lies behind it: where the two shadows touch, neither pin's edges can be seen
    # inside the other's (False: contours drawn or simulated pin by pin).
    pins_opaque: bool = False
    # Set where the two pins' shadows lie on each other: the pins' edge pixels as extracted
    # (both labels), which the fit shares out between the pins (JointProblem.
    # with_pin_edges_shared), and where each pin's own edge could be seen (outside the
    # other's shadow). None: the extraction's names and contours stand.
    pin_edges: np.ndarray | None = None
    pins_visible: dict[str, VisibleRegion] | None = None
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

    def with_contours(self, **contours: np.ndarray) -> ViewObservation:
        """This view with some labels' contours replaced. A distance map depends on its
        contour alone (10-20 ms each), so the new view keeps the maps built of the labels
        not replaced, and of a label handed another's very array (a swap of names)."""
        view = ViewObservation(self.view_id, self.camera, {**self.contours, **contours},
                               self.notes, self.bone_visible, self.bone_edge_search,
                               self.pins_opaque, self.pin_edges, self.pins_visible)
        for label in view.contours:
            given = contours.get(label, self.contours[label])
            built = [other for other, own in self.contours.items()
                     if own is given and other in self._distance_maps]
            if built:
                view._distance_maps[label] = self._distance_maps[built[0]]
        return view

    def distance_map(self, label: str) -> DistanceMap:
        if label not in self._distance_maps:
            self._distance_maps[label] = DistanceMap.from_points(
                self.contours[label], self.camera.width, self.camera.height, MAP_MARGIN_PX)
        return self._distance_maps[label]
