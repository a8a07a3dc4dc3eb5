"""The energy terms of the joint solver (DESIGN.md section 4), with analytic Jacobians.

Each term concerns one view and one rigid body (the bone, or one pin) and returns whitened
residuals (divided by the expected noise ``sigma``) for :mod:`solver.optimizer`:

- :class:`ReprojectionTerm` (E_rp): a 3D edge point, posed and projected, lands on the
  pixel where it was observed. Touches the view pose, the pin pose (for pins) and the point.
- :class:`BackProjectionTerm` (E_bp): a 3D edge point lies on its model's surface (signed
  distance field). Touches only the point.
- :class:`ModelProjectionTerm` (E_mp): the model's silhouette, projected with the current
  poses, lies on the observed contour (distance map). Touches the view pose and pin pose.

Pose indices refer to ``State.poses``; a body index of ``None`` means the bone, whose frame
is the tibia frame itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .camera import Camera
from .geometry import hat
from .observations import DistanceMap
from .optimizer import Linearization, RobustLoss, State
from .silhouette import ContourGenerator
from .sdf import SignedDistanceField

__all__ = ["ReprojectionTerm", "BackProjectionTerm", "ModelProjectionTerm", "posed_in_camera"]


def posed_in_camera(
    state: State, view: int, body: int | None, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Camera-frame positions of body-frame points and their Jacobians.

    Returns ``p_cam`` (N, 3), ``d p_cam / d xi_view`` (N, 3, 6), ``d p_cam / d xi_body``
    (N, 3, 6) or None for the bone, and ``d p_cam / d X`` (3, 3) (shared by all points).
    """
    T_view = state.poses[view]
    if body is None:
        p_tibia, J_body, R_chain = X, None, T_view.R
    else:
        T_body = state.poses[body]
        p_tibia = T_body.apply(X)
        local = np.concatenate(
            [np.broadcast_to(T_body.R, (len(X), 3, 3)), -T_body.R @ hat(X)], axis=2
        )
        J_body = T_view.R @ local
        R_chain = T_view.R @ T_body.R
    p_cam = T_view.apply(p_tibia)
    J_view = np.concatenate(
        [np.broadcast_to(T_view.R, (len(X), 3, 3)), -T_view.R @ hat(p_tibia)], axis=2
    )
    return p_cam, J_view, J_body, R_chain


def _pose_jacobians(view: int, body: int | None, n: int, J_view: np.ndarray,
                    J_body: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray]]:
    out = [(np.full(n, view), J_view)]
    if body is not None:
        out.append((np.full(n, body), J_body))
    return out


@dataclass
class ReprojectionTerm:
    """E_rp for the edge points ``point_ids`` observed at ``pixels`` in one view."""

    name: str
    view: int
    body: int | None
    camera: Camera
    pixels: np.ndarray  # (N, 2)
    point_ids: np.ndarray  # (N,)
    sigma_px: float
    weight: float = 1.0
    loss: RobustLoss = RobustLoss("huber", 2.0)

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        X = state.points[self.point_ids]
        p_cam, J_view, J_body, R_chain = posed_in_camera(state, self.view, self.body, X)
        uv, J_proj = self.camera.project_with_jacobian(p_cam)
        r = (uv - self.pixels) / self.sigma_px
        if not jacobians:
            return Linearization(r)
        J_proj = J_proj / self.sigma_px
        J_b = None if J_body is None else J_proj @ J_body
        return Linearization(
            r,
            _pose_jacobians(self.view, self.body, len(X), J_proj @ J_view, J_b),
            (self.point_ids, J_proj @ R_chain),
        )


@dataclass
class BackProjectionTerm:
    """E_bp: signed distance of the edge points ``point_ids`` to their model's surface."""

    name: str
    sdf: SignedDistanceField
    point_ids: np.ndarray
    sigma_mm: float
    weight: float = 1.0
    loss: RobustLoss = RobustLoss("huber", 2.0)

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        d, grad = self.sdf.query(state.points[self.point_ids])
        r = d[:, None] / self.sigma_mm
        if not jacobians:
            return Linearization(r)
        return Linearization(r, [], (self.point_ids, grad[:, None, :] / self.sigma_mm))


@dataclass
class ModelProjectionTerm:
    """E_mp: the projected model silhouette and the observed contour lie on each other.

    Two-sided, so that neither can be ignored: every silhouette point inside the field of
    view is charged its distance to the observed contour (distance map), and every observed
    contour pixel its distance to the nearest projected silhouette point. A one-sided cost
    could be lowered by sliding the model out of the field of view.
    """

    name: str
    view: int
    body: int | None
    camera: Camera
    contour: ContourGenerator
    distance_map: DistanceMap
    observed: np.ndarray  # (M, 2) observed contour pixels of this body
    sigma_px: float
    spacing_px: float = 3.0
    outer_only: bool = True
    weight: float = 1.0
    loss: RobustLoss = RobustLoss("cauchy", 3.0)

    def _T_cam_body(self, state: State):
        T = state.poses[self.view]
        return T if self.body is None else T @ state.poses[self.body]

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        S = self.contour.outline_points(self._T_cam_body(state), self.camera, self.spacing_px,
                                        outer_only=self.outer_only)
        if len(S) == 0:
            # Nothing of the model is in view: every observed pixel is unexplained.
            r = np.full((len(self.observed), 1), self.camera.width / self.sigma_px)
            return Linearization(r)
        p_cam, J_view, J_body, _ = posed_in_camera(state, self.view, self.body, S)
        uv, J_proj = self.camera.project_with_jacobian(p_cam)
        dist, grad = self.distance_map.query(uv)
        nearest_dist, nearest = cKDTree(uv).query(self.observed)
        r = np.concatenate([dist, nearest_dist])[:, None] / self.sigma_px
        if not jacobians:
            return Linearization(r)
        direction = (uv[nearest] - self.observed) / np.maximum(nearest_dist, 1e-9)[:, None]
        rows = np.concatenate([np.arange(len(S)), nearest])
        J_pix = np.concatenate([grad, direction])[:, None, :] / self.sigma_px  # (N, 1, 2)
        J_dist = J_pix @ J_proj[rows]  # (N, 1, 3)
        J_b = None if J_body is None else J_dist @ J_body[rows]
        return Linearization(r, _pose_jacobians(self.view, self.body, len(rows),
                                                J_dist @ J_view[rows], J_b))
