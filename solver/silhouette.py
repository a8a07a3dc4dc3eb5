"""Occluding contours (silhouettes) of posed meshes, vectorised.

An X-ray shows a bone's outline where rays graze its surface. On a triangle mesh those are
the edges shared by a face turned towards the X-ray source and one turned away (contour
generators). Interior folds of the surface also produce contour generators, but only the
*outer* outline is observed as the bone's contour, so generators are kept only where they
project onto the boundary of the model's projected footprint.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import trimesh

from .camera import Camera
from .geometry import Pose, box_corners

__all__ = ["ContourGenerator", "INTERIOR_REUSE_PX"]

# Projected footprints are rasterised at 1/_MASK_DOWNSCALE resolution; cv2.fillPoly's shift
# keeps _SUBPIXEL_BITS of sub-pixel precision in the vertex coordinates.
_MASK_DOWNSCALE = 4
# The interior mask is eroded by one mask pixel, so it stays valid while the model moves by
# less than half of that in the image (see ContourGenerator.interior).
INTERIOR_REUSE_PX = _MASK_DOWNSCALE / 2
_SUBPIXEL_BITS = 4


@dataclass(frozen=True)
class ContourGenerator:
    """Precomputed mesh topology for fast silhouette queries in the model's frame."""

    vertices: np.ndarray  # (V, 3) model frame, mm
    faces: np.ndarray  # (F, 3)
    face_normals: np.ndarray  # (F, 3)
    face_centres: np.ndarray  # (F, 3)
    adjacent_faces: np.ndarray  # (E, 2) faces sharing each interior edge
    adjacent_edges: np.ndarray  # (E, 2) vertex indices of that edge

    @staticmethod
    def from_mesh(mesh: trimesh.Trimesh) -> ContourGenerator:
        return ContourGenerator(
            vertices=np.asarray(mesh.vertices, float),
            faces=np.asarray(mesh.faces, np.int64),
            face_normals=np.asarray(mesh.face_normals, float),
            face_centres=np.asarray(mesh.triangles_center, float),
            adjacent_faces=np.asarray(mesh.face_adjacency, np.int64),
            adjacent_edges=np.asarray(mesh.face_adjacency_edges, np.int64),
        )

    def _front_facing(self, source_in_model: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", self.face_centres - source_in_model, self.face_normals) < 0

    def footprint(self, T_cam_model: Pose, camera: Camera, downscale: int = _MASK_DOWNSCALE) -> np.ndarray:
        """Binary mask (uint8, 1/downscale resolution) of the model's projection."""
        front = self._front_facing(T_cam_model.inverse().t)
        uv = camera.project(T_cam_model.apply(self.vertices))
        tri = uv[self.faces[front]] / downscale
        pts = np.round(tri * (1 << _SUBPIXEL_BITS)).astype(np.int32)
        height = -(-camera.height // downscale)
        width = -(-camera.width // downscale)
        mask = np.zeros((height, width), np.uint8)
        # Triangles are drawn one polygon each so overlaps fill as a union, not even-odd.
        cv2.fillPoly(mask, list(pts.reshape(-1, 3, 1, 2)), 1, lineType=cv2.LINE_8,
                     shift=_SUBPIXEL_BITS)
        return mask

    @cached_property
    def bounding_box_corners(self) -> np.ndarray:
        """(8, 3) corners of the model's bounding box, model frame (computed once)."""
        return box_corners(self.vertices.min(axis=0), self.vertices.max(axis=0))

    def image_motion_px(self, T_a: Pose, T_b: Pose, camera: Camera) -> float:
        """Largest image displacement of the model's bounding-box corners between two poses:
        a bound on how far any of its points moved in the image."""
        corners = self.bounding_box_corners
        uv_a, uv_b = camera.project(T_a.apply(corners)), camera.project(T_b.apply(corners))
        return float(np.max(np.linalg.norm(uv_a - uv_b, axis=1)))

    def interior(self, T_cam_model: Pose, camera: Camera) -> np.ndarray:
        """Mask (1/4 resolution) of the footprint's interior, more than a mask pixel deep.

        Contour generators that project into it are interior folds, not the outer outline.
        It changes slowly with the pose, so callers may reuse it for nearby poses."""
        return cv2.erode(self.footprint(T_cam_model, camera), np.ones((3, 3), np.uint8))

    def outline_points(
        self,
        T_cam_model: Pose,
        camera: Camera,
        spacing_px: float,
        outer_only: bool = True,
        fov_margin_px: float = 2.0,
        interior: np.ndarray | None = None,
    ) -> np.ndarray:
        """Model-frame points (N, 3) sampled every ~``spacing_px`` along the visible outline.

        Only points projecting inside the camera's field of view are returned; with
        ``outer_only`` interior folds are dropped, using ``interior`` (see :meth:`interior`)
        when given, else the footprint of this pose.
        """
        source = T_cam_model.inverse().t
        front = self._front_facing(source)
        on_contour = front[self.adjacent_faces[:, 0]] != front[self.adjacent_faces[:, 1]]
        edges = self.adjacent_edges[on_contour]
        if len(edges) == 0:
            return np.zeros((0, 3))
        a, b = self.vertices[edges[:, 0]], self.vertices[edges[:, 1]]
        uv_a = camera.project(T_cam_model.apply(a))
        uv_b = camera.project(T_cam_model.apply(b))
        counts = np.maximum(1, np.ceil(np.linalg.norm(uv_b - uv_a, axis=1) / spacing_px)).astype(int)
        edge_index = np.repeat(np.arange(len(edges)), counts)
        # Sample at the centres of equal sub-segments, so shared end-points are not doubled.
        starts = np.cumsum(counts) - counts
        s = (np.arange(counts.sum()) - starts[edge_index] + 0.5) / counts[edge_index]
        points = a[edge_index] + s[:, None] * (b[edge_index] - a[edge_index])
        uv = uv_a[edge_index] + s[:, None] * (uv_b[edge_index] - uv_a[edge_index])

        keep = camera.in_field(uv, fov_margin_px)
        if outer_only and np.any(keep):
            if interior is None:
                interior = self.interior(T_cam_model, camera)
            pix = np.clip(np.round(uv / _MASK_DOWNSCALE).astype(int), 0,
                          np.array(interior.shape[::-1]) - 1)
            keep &= interior[pix[:, 1], pix[:, 0]] == 0
        return points[keep]
