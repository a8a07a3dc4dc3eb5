"""The energy terms of the joint solver (docs/solver.md), with analytic Jacobians.

Each term concerns one view and one rigid body (the bone, or one pin) and returns its
residuals in their own units (pixels, millimetres, radians) for :mod:`solver.optimizer`,
which whitens and charges them by the term's :class:`~slamtka.solver.optimizer.NoiseModel`:

- :class:`ReprojectionTerm` (E_rp): a 3D edge point, posed and projected, lands on the
  pixel where it was observed. Touches the view pose, the pin pose (for pins) and the point.
- :class:`BackProjectionTerm` (E_bp): a 3D edge point lies on its model's surface (signed
  distance field). Touches only the point.
- :class:`ModelProjectionTerm` (E_mp): the model's silhouette, projected with the current
  poses, lies on the observed contour (distance map). Touches the view pose and pin pose.
- :class:`RelativePoseTerm` (E_odo): the motion of the C-arm between two views agrees with
  what its joint encoders measured. Touches both view poses.

Terms name the poses they touch by key (:mod:`.variables`): a view, and a body that is a pin
or :data:`~slamtka.solver.variables.BONE`, whose frame is the tibia frame itself (no pose to
estimate, so no Jacobian block).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from slamtka.solver.camera import MIN_DEPTH_MM, Camera
from slamtka.solver.geometry import Pose, hat, so3_log, so3_right_jacobian_inverse
from slamtka.solver.kernels import nearest_points, pose_rows, silhouette_rows, surface_rows
from slamtka.solver.observations import DistanceMap, VisibleRegion
from slamtka.solver.optimizer import Linearization, NoiseModel, State
from slamtka.solver.sdf import SignedDistanceField
from slamtka.solver.silhouette import INTERIOR_REUSE_PX, ContourGenerator
from slamtka.solver.variables import BONE, PoseKey

__all__ = ["Correspondence", "ReprojectionTerm", "BackProjectionTerm", "ModelProjectionTerm", "RelativePoseTerm",
           "pose_in_view", "pose_increments", "projected"]


def pose_increments(
    state: State, view: PoseKey, body: PoseKey, X: np.ndarray, G_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Jacobians with respect to the view and body poses of quantities whose gradient with
    respect to the camera-frame point ``T X`` is ``G_cam`` (N, ..., 3), at body-frame points
    ``X`` (N, 3).

    Returns ``d / d xi_view`` (N, ..., 6), ``d / d xi_body`` (N, ..., 6) or None for the
    bone, and the gradient with respect to ``X`` (N, ..., 3). A right increment
    ``(rho, phi)`` of a pose ``T`` moves ``T p`` by ``R rho - R [p]x phi``; for a row ``g``
    of ``G_cam R`` the second block is ``-g [p]x = (p x g)``, which is how the blocks are
    formed without a batched product per point (:func:`~slamtka.solver.kernels.pose_rows`).
    """
    with_body = body != BONE
    T_body = state.poses[body] if with_body else state.poses[view]  # any pose: unused for the bone
    J_view, J_body, G_x = pose_rows(
        np.ascontiguousarray(G_cam, float).reshape(len(G_cam), -1, 3), np.ascontiguousarray(X, float),
        np.ascontiguousarray(state.poses[view].R), np.ascontiguousarray(T_body.R),
        np.ascontiguousarray(T_body.t, float), with_body)
    rows = G_cam.shape[:-1]
    return (J_view.reshape(rows + (6,)), J_body.reshape(rows + (6,)) if with_body else None,
            G_x.reshape(rows + (3,)))


def pose_in_view(poses: Mapping[PoseKey, Pose], view: PoseKey, body: PoseKey) -> Pose:
    """The pose of ``body`` in ``view``'s camera frame at ``poses``."""
    T_view = poses[view]
    return T_view if body == BONE else T_view @ poses[body]


def projected(
    state: State, view: PoseKey, body: PoseKey, X: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """Pixels of body-frame points and their Jacobians.

    Returns ``uv`` (N, 2), ``d uv / d xi_view`` (N, 2, 6), ``d uv / d xi_body`` (N, 2, 6) or
    None for the bone, and ``d uv / d X`` (N, 2, 3) (see :func:`pose_increments`).
    """
    uv, J_proj = camera.project_with_jacobian(pose_in_view(state.poses, view, body).apply(X))
    return (uv,) + pose_increments(state, view, body, X, J_proj)


def _pose_jacobians(view: PoseKey, body: PoseKey, J_view: np.ndarray,
                    J_body: np.ndarray | None) -> list[tuple[PoseKey, np.ndarray]]:
    """The Jacobian blocks by key: the bone's frame has none."""
    if J_body is None:
        return [(view, J_view)]
    return [(view, J_view), (body, J_body)]


@dataclass
class ReprojectionTerm:
    """E_rp for the edge points ``point_ids`` observed at ``pixels`` in one view."""

    name: str
    view: PoseKey
    body: PoseKey
    camera: Camera
    pixels: np.ndarray  # (N, 2)
    point_ids: np.ndarray  # (N,)
    noise: NoiseModel  # sigma in pixels

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        X = state.points[self.point_ids]
        if not jacobians:  # trial steps: half of all evaluations
            uv = self.camera.project(pose_in_view(state.poses, self.view, self.body).apply(X))
            return Linearization(uv - self.pixels)
        uv, J_view, J_body, J_point = projected(state, self.view, self.body, X, self.camera)
        return Linearization(uv - self.pixels, _pose_jacobians(self.view, self.body, J_view, J_body),
                             (self.point_ids, J_point))


@dataclass
class BackProjectionTerm:
    """E_bp: the edge points ``point_ids`` are where their rays graze the model's surface.

    Two residuals per point: its signed distance to the surface, and how far it has moved
    along its ray (``ray_directions``, model frame) from where it was seated (``seated``),
    where the ray passes closest to or deepest into the model. Without the second a point
    whose ray cuts into the model (a contour pixel inside the silhouette) could slide to
    where the ray enters the surface and cost nothing, so noise inside the outline would
    be free and noise outside charged, biasing the fit; at the seated depth the distance
    along the ray is stationary, so holding it there is right to first order.
    """

    name: str
    sdf: SignedDistanceField
    point_ids: np.ndarray
    ray_directions: np.ndarray  # (N, 3) unit, model frame
    seated: np.ndarray  # (N, 3) model frame
    noise: NoiseModel  # sigmas (mm) of the distance to the surface and along the ray
    # Where the points were observed (view and body keys as in ReprojectionTerm), for
    # reports; the residuals concern the points alone.
    view: PoseKey | None = None
    body: PoseKey | None = None

    def graze_offset_rms_mm(self, state: State) -> float:
        """RMS distance (mm) of the points from where their rays graze the model: off its
        surface, and moved along their rays from the grazing depth (both residuals, in mm)."""
        r = self.linearize(state, jacobians=False).residuals
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) if len(r) else 0.0

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        sdf = self.sdf
        r, J = surface_rows(sdf.values, np.asarray(sdf.origin, float), float(sdf.spacing),
                            np.ascontiguousarray(state.points, float), np.asarray(self.point_ids, np.int64),
                            np.ascontiguousarray(self.seated, float),
                            np.ascontiguousarray(self.ray_directions, float), jacobians)
        if not jacobians:
            return Linearization(r)
        return Linearization(r, [], (self.point_ids, J))


@dataclass(frozen=True)
class Correspondence:
    """What a silhouette term pairs at one linearisation point: its traced outline (model
    frame), the outline points charged for lying off the contour (those where the frame
    could show an edge), and, per observed contour pixel, the outline point nearest it."""

    outline: np.ndarray  # (S, 3)
    charged: np.ndarray  # (C,) indices into ``outline``
    nearest: np.ndarray | None  # (M,) indices into ``outline``; None for an empty outline


@dataclass
class ModelProjectionTerm:
    """E_mp: the projected model silhouette and the observed contour lie on each other.

    The silhouette and its pairing with the observed pixels (:class:`Correspondence`) are
    chosen by :meth:`correspond`, the explicit correspondence step the optimiser takes once
    per iteration (tracing is the expensive part), and held while steps are tried, the usual
    fixed-correspondence approximation. With ``freeze_outline`` the outline is traced at the
    first step and then held (only the pairing is chosen again), for a final refinement that
    starts from converged silhouettes: that problem is smooth, so its convergence tests are
    meaningful.

    Two-sided, so that neither can be ignored: every silhouette point inside the field of
    view is charged its distance to the observed contour (distance map), and every observed
    contour pixel its distance to the nearest projected silhouette point. A one-sided cost
    could be lowered by sliding the model out of the field of view. A held pairing can only
    overstate a trial's cost, so a step accepted on it is a true decrease.

    Where the frame could not show the edge (``visible``: metal, collimator blades, text,
    the pins' shadows) a silhouette point is not charged: its contour is hidden, not
    missing. It still pairs with observed pixels, which all lie where edges can be seen.
    """

    name: str
    view: PoseKey
    body: PoseKey
    camera: Camera
    contour: ContourGenerator
    distance_map: DistanceMap
    observed: np.ndarray  # (M, 2) observed contour pixels of this body
    noise: NoiseModel  # sigma in pixels
    spacing_px: float = 3.0
    outer_only: bool = True
    freeze_outline: bool = False
    visible: VisibleRegion | None = None
    correspondence: Correspondence | None = field(default=None, init=False, repr=False)
    # The footprint that tells the outer outline from interior folds, and the pose it was
    # rasterised at: a cache of :meth:`correspond`, redone once the model has moved enough.
    _interior: tuple[Pose, np.ndarray] | None = field(default=None, init=False, repr=False)

    def _trace(self, T_cam_body: Pose) -> np.ndarray:
        """Model-frame outline points at ``T_cam_body``."""
        interior = None
        if self.outer_only:
            if self._interior is None or self.contour.image_motion_px(
                    self._interior[0], T_cam_body, self.camera) > INTERIOR_REUSE_PX:
                self._interior = (T_cam_body, self.contour.interior(T_cam_body, self.camera))
            interior = self._interior[1]
        return self.contour.outline_points(T_cam_body, self.camera, self.spacing_px,
                                           outer_only=self.outer_only, interior=interior)

    def correspond(self, state: State) -> None:
        """The correspondence step at ``state``: the outline traced (unless frozen and
        traced already) and each observed pixel paired with its nearest outline point."""
        T_cam_body = pose_in_view(state.poses, self.view, self.body)
        held = self.correspondence
        S = held.outline if held is not None and self.freeze_outline else self._trace(T_cam_body)
        nearest, charged = None, np.arange(len(S))
        if len(S):
            uv = self.camera.project(T_cam_body.apply(S))
            # Binned at twice the outline's spacing: a few points per occupied cell.
            nearest = nearest_points(uv, self.observed, 2.0 * self.spacing_px)
            if self.visible is not None:
                charged = np.flatnonzero(self.visible.contains(uv))
        self.correspondence = Correspondence(S, charged, nearest)

    def distances_px(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        """Pixel distances of the visible outline traced at ``state`` to the observed
        contour, and of each observed contour pixel to the outline (the two sides of the
        residual)."""
        self.correspond(state)
        r = np.abs(self.linearize(state, jacobians=False).residuals[:, 0])
        return r[: len(r) - len(self.observed)], r[len(r) - len(self.observed):]

    def visible_share(self) -> float:
        """The share of the outline of the last correspondence step where the frame could
        show its edge (1 for an empty outline)."""
        held = self.correspondence
        if held is None or len(held.outline) == 0:
            return 1.0
        return len(held.charged) / len(held.outline)

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        if self.correspondence is None:
            raise RuntimeError("a silhouette term is linearised after its correspondence step")
        T_cam_body = pose_in_view(state.poses, self.view, self.body)
        S, nearest = self.correspondence.outline, self.correspondence.nearest
        charged = self.correspondence.charged
        if nearest is None:
            # Nothing of the model is in view: every observed pixel is unexplained.
            r = np.full((len(self.observed), 1), float(self.camera.width))
            return Linearization(r)
        # The residuals and d r / d p_cam = (d r / d uv) (d uv / d p_cam) in one compiled
        # pass, for the silhouette's own points and for the silhouette point nearest each
        # observed pixel; d p_cam / d xi follows for one row per residual.
        r, J_cam = silhouette_rows(T_cam_body.apply(S), *self.camera.intrinsics, MIN_DEPTH_MM,
                                   self.distance_map.values, self.distance_map.origin_uv, charged,
                                   nearest, self.observed, jacobians)
        if not jacobians:
            return Linearization(r)
        rows = np.concatenate([charged, nearest])
        J_view, J_body, _ = pose_increments(state, self.view, self.body, S[rows], J_cam)
        J_b = None if J_body is None else J_body[:, None, :]
        return Linearization(r, _pose_jacobians(self.view, self.body, J_view[:, None, :], J_b))


@dataclass
class RelativePoseTerm:
    """E_odo: two views see the tibia where the encoders' relative C-arm motion says.

    ``measured`` is the encoder motion ``T_camB_camA`` between the views. The discrepancy
    ``D = A^-1 T_A^-1 M^-1 T_B A`` is the tibia's pose seen from view B and carried back to
    view A, expressed in the anatomical frame ``anchor`` (``T_tibia_anat``), so that its
    rotation is about the knee centre and its translation is at the knee, where the
    encoder uncertainty (the noise model's sigmas, mm and rad) is stated. The residual is
    ``(t_D, log R_D)``. Its Jacobians follow from how the right
    increments ``E = (rho, phi)`` of the views move ``D``: ``T_B E`` gives ``D (A^-1 E A)``
    and ``T_A E`` gives ``(A^-1 E^-1 A) D``, to first order a right and a left increment of
    ``D`` by the increment carried into the anchor frame.
    """

    name: str
    view_a: PoseKey
    view_b: PoseKey
    measured: Pose
    anchor: Pose
    noise: NoiseModel  # sigmas of the translation (mm, x3) and the rotation (rad, x3)

    def _discrepancy(self, T_a: Pose, T_b: Pose) -> Pose:
        return self.anchor.inverse() @ T_a.inverse() @ self.measured.inverse() @ T_b @ self.anchor

    def linearize(self, state: State, jacobians: bool = True) -> Linearization:
        D = self._discrepancy(state.poses[self.view_a], state.poses[self.view_b])
        phi = so3_log(D.R)
        r = np.concatenate([D.t, phi])[None, :]
        if not jacobians:
            return Linearization(r)
        R_inv, t_hat = self.anchor.R.T, hat(self.anchor.t)  # A^-1's rotation, [t_A]x
        right_inv = so3_right_jacobian_inverse(phi)
        left_inv = so3_right_jacobian_inverse(-phi)
        J_a = np.zeros((6, 6))
        J_a[:3, :3] = -R_inv
        J_a[:3, 3:] = hat(D.t) @ R_inv + R_inv @ t_hat
        J_a[3:, 3:] = -left_inv @ R_inv
        J_b = np.zeros((6, 6))
        J_b[:3, :3] = D.R @ R_inv
        J_b[:3, 3:] = -D.R @ R_inv @ t_hat
        J_b[3:, 3:] = right_inv @ R_inv
        return Linearization(r, [(self.view_a, J_a[None]), (self.view_b, J_b[None])])
