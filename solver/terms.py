"""The energy terms of the joint solver (DESIGN.md section 4), with analytic Jacobians.

Each term concerns one view and one rigid body (the bone, or one pin) and returns whitened
residuals (divided by the expected noise ``sigma``) for :mod:`solver.optimizer`:

- :class:`ReprojectionTerm` (E_rp): a 3D edge point, posed and projected, lands on the
  pixel where it was observed. Touches the view pose, the pin pose (for pins) and the point.
- :class:`BackProjectionTerm` (E_bp): a 3D edge point lies on its model's surface (signed
  distance field). Touches only the point.
- :class:`ModelProjectionTerm` (E_mp): the model's silhouette, projected with the current
  poses, lies on the observed contour (distance map). Touches the view pose and pin pose.
- :class:`RelativePoseTerm` (E_odo): the motion of the C-arm between two views agrees with
  what its joint encoders measured. Touches both view poses.

Pose indices refer to ``State.poses``; a body index of ``None`` means the bone, whose frame
is the tibia frame itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .camera import Camera
from .geometry import Pose, hat, so3_log, so3_right_jacobian_inverse
from .observations import DistanceMap
from .optimizer import Linearization, RobustLoss, State
from .silhouette import INTERIOR_REUSE_PX, ContourGenerator
from .sdf import SignedDistanceField

__all__ = ["ReprojectionTerm", "BackProjectionTerm", "ModelProjectionTerm", "RelativePoseTerm",
           "posed_in_camera"]


def posed_in_camera(
    state: State, view: int, body: int | None, X: np.ndarray, jacobians: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Camera-frame positions of body-frame points and their Jacobians.

    Returns ``p_cam`` (N, 3), ``d p_cam / d xi_view`` (N, 3, 6), ``d p_cam / d xi_body``
    (N, 3, 6) or None for the bone, and ``d p_cam / d X`` (3, 3) (shared by all points).
    Without ``jacobians`` (trial steps: half of all evaluations) only ``p_cam`` is computed
    and the rest is None.
    """
    T_view = state.poses[view]
    if not jacobians:
        T = T_view if body is None else T_view @ state.poses[body]
        return T.apply(X), None, None, None
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


def _pose_jacobians(view: int, body: int | None, J_view: np.ndarray,
                    J_body: np.ndarray | None) -> list[tuple[int, np.ndarray]]:
    return [(view, J_view)] if body is None else [(view, J_view), (body, J_body)]


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
        p_cam, J_view, J_body, R_chain = posed_in_camera(state, self.view, self.body, X, jacobians)
        uv, J_proj = (self.camera.project_with_jacobian(p_cam) if jacobians
                      else (self.camera.project(p_cam), None))
        r = (uv - self.pixels) / self.sigma_px
        if not jacobians:
            return Linearization(r)
        J_proj = J_proj / self.sigma_px
        J_b = None if J_body is None else J_proj @ J_body
        return Linearization(
            r,
            _pose_jacobians(self.view, self.body, J_proj @ J_view, J_b),
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

    The silhouette is traced when Jacobians are requested (once per optimiser iteration)
    and its model-frame points are held while steps are tried, the usual fixed-
    correspondence approximation (tracing is the expensive part). With ``freeze_outline``
    it is traced once and then held, for a final refinement that starts from converged
    silhouettes: that problem is smooth, so its convergence tests are meaningful.

    Two-sided, so that neither can be ignored: every silhouette point inside the field of
    view is charged its distance to the observed contour (distance map), and every observed
    contour pixel its distance to the nearest projected silhouette point. A one-sided cost
    could be lowered by sliding the model out of the field of view. The nearest points are
    searched when Jacobians are requested and held while steps are tried: a held pairing
    can only overstate a trial's cost, so a step accepted on it is a true decrease.
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
    freeze_outline: bool = False
    _outline: np.ndarray | None = field(default=None, init=False, repr=False)
    _interior: tuple[Pose, np.ndarray] | None = field(default=None, init=False, repr=False)
    _nearest: np.ndarray | None = field(default=None, init=False, repr=False)

    def _T_cam_body(self, state: State):
        T = state.poses[self.view]
        return T if self.body is None else T @ state.poses[self.body]

    def _trace(self, T_cam_body: Pose) -> np.ndarray:
        """Model-frame outline points; the footprint interior that tells the outer outline
        from interior folds is rasterised again only once the model has moved enough."""
        interior = None
        if self.outer_only:
            if self._interior is None or self.contour.image_motion_px(
                    self._interior[0], T_cam_body, self.camera) > INTERIOR_REUSE_PX:
                self._interior = (T_cam_body, self.contour.interior(T_cam_body, self.camera))
            interior = self._interior[1]
        return self.contour.outline_points(T_cam_body, self.camera, self.spacing_px,
                                           outer_only=self.outer_only, interior=interior)

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        if self._outline is None or (jacobians and not self.freeze_outline):
            self._outline = self._trace(self._T_cam_body(state))
            self._nearest = None
        S = self._outline
        if len(S) == 0:
            # Nothing of the model is in view: every observed pixel is unexplained.
            r = np.full((len(self.observed), 1), self.camera.width / self.sigma_px)
            return Linearization(r)
        p_cam, J_view, J_body, _ = posed_in_camera(state, self.view, self.body, S, jacobians)
        uv, J_proj = (self.camera.project_with_jacobian(p_cam) if jacobians
                      else (self.camera.project(p_cam), None))
        dist, grad = self.distance_map.query(uv)
        if jacobians or self._nearest is None:
            self._nearest = cKDTree(uv).query(self.observed)[1]
        nearest = self._nearest
        nearest_dist = np.linalg.norm(uv[nearest] - self.observed, axis=1)
        r = np.concatenate([dist, nearest_dist])[:, None] / self.sigma_px
        if not jacobians:
            return Linearization(r)
        direction = (uv[nearest] - self.observed) / np.maximum(nearest_dist, 1e-9)[:, None]
        rows = np.concatenate([np.arange(len(S)), nearest])
        J_pix = np.concatenate([grad, direction])[:, None, :] / self.sigma_px  # (N, 1, 2)
        J_dist = J_pix @ J_proj[rows]  # (N, 1, 3)
        J_b = None if J_body is None else J_dist @ J_body[rows]
        return Linearization(r, _pose_jacobians(self.view, self.body, J_dist @ J_view[rows], J_b))


@dataclass
class RelativePoseTerm:
    """E_odo: two views see the tibia where the encoders' relative C-arm motion says.

    ``measured`` is the encoder motion ``T_camB_camA`` between the views. The discrepancy
    ``D = A^-1 T_A^-1 M^-1 T_B A`` is the tibia's pose seen from view B and carried back to
    view A, expressed in the anatomical frame ``anchor`` (``T_tibia_anat``), so that its
    rotation is about the knee centre and its translation is at the knee, where the
    encoder uncertainty (``sigma_rad``, ``sigma_mm``) is stated. The residual is
    ``(t_D / sigma_mm, log R_D / sigma_rad)``. Its Jacobians follow from how the right
    increments ``E = (rho, phi)`` of the views move ``D``: ``T_B E`` gives ``D (A^-1 E A)``
    and ``T_A E`` gives ``(A^-1 E^-1 A) D``, to first order a right and a left increment of
    ``D`` by the increment carried into the anchor frame.
    """

    name: str
    view_a: int
    view_b: int
    measured: Pose
    anchor: Pose
    sigma_rad: float
    sigma_mm: float
    weight: float = 1.0
    loss: RobustLoss = RobustLoss("l2", 1.0)

    def _discrepancy(self, T_a: Pose, T_b: Pose) -> Pose:
        return self.anchor.inverse() @ T_a.inverse() @ self.measured.inverse() @ T_b @ self.anchor

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        D = self._discrepancy(state.poses[self.view_a], state.poses[self.view_b])
        phi = so3_log(D.R)
        r = np.concatenate([D.t / self.sigma_mm, phi / self.sigma_rad])[None, :]
        if not jacobians:
            return Linearization(r)
        R_A, t_A = self.anchor.R.T, hat(self.anchor.t)  # R_A is A^-1's rotation
        right_inv = so3_right_jacobian_inverse(phi)
        left_inv = so3_right_jacobian_inverse(-phi)
        J_a = np.zeros((6, 6))
        J_a[:3, :3] = -R_A
        J_a[:3, 3:] = hat(D.t) @ R_A + R_A @ t_A
        J_a[3:, 3:] = -left_inv @ R_A
        J_b = np.zeros((6, 6))
        J_b[:3, :3] = D.R @ R_A
        J_b[:3, 3:] = -D.R @ R_A @ t_A
        J_b[3:, 3:] = right_inv @ R_A
        scale = np.repeat([1.0 / self.sigma_mm, 1.0 / self.sigma_rad], 3)[:, None]
        J_a, J_b = scale * J_a, scale * J_b
        return Linearization(r, [(self.view_a, J_a[None]), (self.view_b, J_b[None])])
