"""Occluding contours (silhouettes) of posed meshes, vectorised.

An X-ray shows a bone's outline where rays graze its surface. On a triangle mesh those are
the edges shared by a face turned towards the X-ray source and one turned away (contour
generators). Interior folds of the surface also produce contour generators, but only the
*outer* outline is observed as the bone's contour, so generators are kept only where they
project onto the boundary of the model's projected footprint.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cached_property
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, box_corners, row_norms
from slamtka.solver.kernels import contour_generators, footprint_mask, outline_samples

if TYPE_CHECKING:
    import trimesh

__all__ = ["ContourGenerator", "INTERIOR_REUSE_PX", "simplified"]

# Projected footprints are rasterised at 1/_MASK_DOWNSCALE resolution.
_MASK_DOWNSCALE = 4
# The interior mask is eroded by one mask pixel, so it stays valid while the model moves by
# less than half of that in the image (see ContourGenerator.interior).
INTERIOR_REUSE_PX = _MASK_DOWNSCALE / 2


def simplified(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """``mesh`` decimated to at most ``max_faces`` faces (itself when it has no more)."""
    if len(mesh.faces) <= max_faces:
        return mesh
    return mesh.simplify_quadric_decimation(face_count=max_faces)


@dataclass(frozen=True)
class ContourGenerator:
    """Precomputed mesh topology for fast silhouette queries in the model's frame."""

    vertices: np.ndarray  # (V, 3) model frame, mm
    faces: np.ndarray  # (F, 3)
    face_normals: np.ndarray  # (F, 3)
    face_centres: np.ndarray  # (F, 3)
    adjacent_faces: np.ndarray  # (E, 2) faces sharing each interior edge
    adjacent_edges: np.ndarray  # (E, 2) vertex indices of that edge, as the first face runs it
    open_edges: np.ndarray  # (B, 2) edges of one face only (open meshes), as that face runs them
    open_edge_faces: np.ndarray  # (B,) that face

    @staticmethod
    def from_mesh(mesh: trimesh.Trimesh) -> ContourGenerator:
        faces = np.asarray(mesh.faces, np.int64)
        adjacent_faces = np.asarray(mesh.face_adjacency, np.int64)
        edges = np.asarray(mesh.face_adjacency_edges, np.int64)
        # Orient each shared edge as its first face runs it (the second runs it backwards).
        first = faces[adjacent_faces[:, 0]]
        forward = np.any((first == edges[:, :1]) & (np.roll(first, -1, axis=1) == edges[:, 1:]),
                         axis=1)
        edges = np.where(forward[:, None], edges, edges[:, ::-1])
        # Edges used by one face only: every directed face edge whose reverse is not one.
        directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
        n = len(mesh.vertices)
        keys = directed[:, 0] * n + directed[:, 1]
        is_open = ~np.isin(directed[:, 1] * n + directed[:, 0], keys)
        return ContourGenerator(
            vertices=np.asarray(mesh.vertices, float),
            faces=faces,
            face_normals=np.asarray(mesh.face_normals, float),
            face_centres=np.asarray(mesh.triangles_center, float),
            adjacent_faces=adjacent_faces,
            adjacent_edges=edges,
            open_edges=directed[is_open],
            open_edge_faces=np.repeat(np.arange(len(faces)), 3)[is_open],
        )

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The topology as named arrays (each name prefixed), to store it with a plan."""
        return {prefix + f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_arrays(arrays: Mapping[str, np.ndarray], prefix: str) -> ContourGenerator:
        """The topology stored by :meth:`arrays` under ``prefix``."""
        return ContourGenerator(**{f.name: arrays[prefix + f.name] for f in fields(ContourGenerator)})

    @cached_property
    def _face_offsets(self) -> np.ndarray:
        """Each face's plane offset ``n . c`` (F,): a face is turned towards a source ``s``
        when ``n . s > n . c``, one product per face and query instead of a difference and
        a product."""
        return np.einsum("ij,ij->i", self.face_centres, self.face_normals)

    def _front_facing(self, source_in_model: np.ndarray) -> np.ndarray:
        return self.face_normals @ source_in_model > self._face_offsets

    def _contour_edges(self, T_cam_model: Pose) -> tuple[np.ndarray, np.ndarray]:
        """The contour generators (E, 2), each run as its front-facing face runs it, and the
        front-facing mask of the faces."""
        front = self._front_facing(T_cam_model.inverse().t)
        return contour_generators(front, self.adjacent_faces, self.adjacent_edges), front

    def footprint(self, T_cam_model: Pose, camera: Camera, downscale: int = _MASK_DOWNSCALE) -> np.ndarray:
        """Binary mask (uint8, 1/downscale resolution) of the model's projection.

        The front-facing faces all wind the same way in the image, so the footprint (their
        union) is where the winding number of their boundary is not zero: the contour
        generators (and open mesh edges of front faces), run as their front face runs them.
        The winding number is accumulated along each row from the signed crossings of these
        edges with the row, so the cost grows with the outline, not with the faces, and no
        sliver of a face can leave a pinhole.
        """
        generators, front = self._contour_edges(T_cam_model)
        edges = np.vstack([generators, self.open_edges[front[self.open_edge_faces]]])
        height, width = -(-camera.height // downscale), -(-camera.width // downscale)
        # Both ends of every edge projected at once: each vertex about twice, which costs
        # less than finding the distinct ones.
        uv = (camera.project(T_cam_model.apply(self.vertices[edges.reshape(-1)])) / downscale
              ).reshape(-1, 2, 2)
        return footprint_mask(np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1]),
                              height, width)

    @cached_property
    def bounding_box_corners(self) -> np.ndarray:
        """(8, 3) corners of the model's bounding box, model frame (computed once)."""
        return box_corners(self.vertices.min(axis=0), self.vertices.max(axis=0))

    def image_motion_px(self, T_a: Pose, T_b: Pose, camera: Camera) -> float:
        """Largest image displacement of the model's bounding-box corners between two poses:
        a bound on how far any of its points moved in the image."""
        corners = self.bounding_box_corners
        uv_a, uv_b = camera.project(T_a.apply(corners)), camera.project(T_b.apply(corners))
        return float(np.max(row_norms(uv_a - uv_b)))

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
        edges = self._contour_edges(T_cam_model)[0]
        if len(edges) == 0:
            return np.zeros((0, 3))
        ends = self.vertices[edges]  # (E, 2, 3)
        uv_ends = camera.project(T_cam_model.apply(ends.reshape(-1, 3))).reshape(-1, 2, 2)
        # Sampled at the centres of equal sub-segments, so shared end-points are not doubled;
        # most samples fall on interior folds: only the kept ones are carried to the model.
        mask = np.zeros((0, 0), np.uint8)  # empty: no interior test
        if outer_only:
            mask = self.interior(T_cam_model, camera) if interior is None else interior
        edge_index, s = outline_samples(
            np.ascontiguousarray(uv_ends[:, 0]), uv_ends[:, 1] - uv_ends[:, 0], float(spacing_px),
            camera.width, camera.height, float(fov_margin_px), camera.fov_radius, mask, _MASK_DOWNSCALE)
        a = ends[edge_index, 0]
        return a + s[:, None] * (ends[edge_index, 1] - a)
