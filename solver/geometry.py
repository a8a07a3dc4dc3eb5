"""Rigid-body geometry on SO(3) and SE(3).

Conventions (README.md, Conventions): a pose ``T_a_b`` maps points from frame b into frame a,
``p_a = R_a_b p_b + t_a_b``; millimetres and radians. Poses are optimised through small
right-multiplied increments ``T <- T * Exp(xi)`` with ``xi = (rho, phi)``: ``rho`` a translation
and ``phi`` a rotation vector, both expressed in the pose's *source* frame b. For points that
gives the simple first-order Jacobian ``d(T p)/d(rho, phi) = [R, -R [p]x]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Pose", "hat", "largest_angle_deg", "row_norms", "so3_exp", "so3_log", "so3_right_jacobian_inverse",
           "rotation_about", "look_at"]

_I3 = np.eye(3)


def row_norms(v: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of ``v`` (N, D), without ``np.linalg.norm``'s overhead."""
    return np.sqrt(np.einsum("ij,ij->i", v, v))


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[v]x`` for one (3,) or many (N, 3) vectors."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues), stable near zero."""
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = hat(phi)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return (
        np.eye(3)
        + (np.sin(theta) / theta) * K
        + ((1.0 - np.cos(theta)) / theta**2) * K @ K
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of :func:`so3_exp`)."""
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_theta))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        return 0.5 * w
    if np.pi - theta < 1e-6:
        # Near pi the antisymmetric part vanishes: read the axis off the symmetric part.
        B = 0.5 * (R + np.eye(3))
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        k = int(np.argmax(axis))
        axis = B[k] / max(axis[k], 1e-12)
        return theta * axis / np.linalg.norm(axis)
    return theta / (2.0 * np.sin(theta)) * w


def so3_right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r(phi)^-1``: how ``log(R Exp(psi))`` moves with a small ``psi`` (the left
    Jacobian's inverse is this at ``-phi``)."""
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = hat(phi)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 12.0
    coefficient = 1.0 / theta**2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    return np.eye(3) + 0.5 * K + coefficient * K @ K


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians about ``axis`` (need not be unit)."""
    axis = np.asarray(axis, dtype=float)
    return so3_exp(axis / np.linalg.norm(axis) * angle)


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``T_a_b``: rotation ``R`` (3, 3) and translation ``t`` (3,) in mm."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=float).reshape(3, 3)
        t = np.asarray(self.t, dtype=float).reshape(3)
        # Orthonormal with determinant +1; written out because poses are made in hot loops.
        orthonormal = np.abs(R.T @ R - _I3).max() <= 1e-6
        det = (R[0, 0] * (R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1])
               - R[0, 1] * (R[1, 0] * R[2, 2] - R[1, 2] * R[2, 0])
               + R[0, 2] * (R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]))
        if not orthonormal or det < 0:
            raise ValueError("Pose rotation is not a proper rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @staticmethod
    def _composed(R: np.ndarray, t: np.ndarray) -> Pose:
        """A pose from a rotation that is proper by construction (a product, transpose or
        exponential of proper rotations): skips the check, which hot loops cannot afford."""
        pose = object.__new__(Pose)
        object.__setattr__(pose, "R", R)
        object.__setattr__(pose, "t", t)
        return pose

    @staticmethod
    def identity() -> Pose:
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(M: np.ndarray) -> Pose:
        M = np.asarray(M, dtype=float)
        if M.shape != (4, 4) or not np.allclose(M[3], [0, 0, 0, 1]):
            raise ValueError(f"expected a 4x4 homogeneous rigid transform, got shape {M.shape}")
        return Pose(M[:3, :3], M[:3, 3])

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.R, self.t
        return M

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) points (or one (3,) point) from frame b into frame a."""
        return np.asarray(points, dtype=float) @ self.R.T + self.t

    def rotate(self, vectors: np.ndarray) -> np.ndarray:
        """Map direction vectors (no translation)."""
        return np.asarray(vectors, dtype=float) @ self.R.T

    def inverse(self) -> Pose:
        return Pose._composed(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Pose) -> Pose:
        return Pose._composed(self.R @ other.R, self.R @ other.t + self.t)

    def retract(self, xi: np.ndarray) -> Pose:
        """``T * Exp(xi)`` for a right increment ``xi = (rho, phi)`` in the source frame."""
        xi = np.asarray(xi, dtype=float).reshape(6)
        return Pose._composed(self.R @ so3_exp(xi[3:]), self.R @ xi[:3] + self.t)

    def local(self, other: Pose) -> np.ndarray:
        """The increment ``xi`` with ``self.retract(xi) == other`` (inverse of retract)."""
        dR = self.R.T @ other.R
        return np.concatenate([self.R.T @ (other.t - self.t), so3_log(dR)])

    def rotation_angle_to(self, other: Pose) -> float:
        """Angle in radians of the relative rotation between two poses."""
        return float(np.linalg.norm(so3_log(self.R.T @ other.R)))

    def to_json(self) -> list[list[float]]:
        return self.matrix().tolist()

    @staticmethod
    def from_json(rows: list[list[float]]) -> Pose:
        return Pose.from_matrix(np.asarray(rows, dtype=float))


def largest_angle_deg(directions: np.ndarray) -> float:
    """Largest angle between any two unit vectors (rows), degrees; 0 for fewer than two."""
    if len(directions) < 2:
        return 0.0
    cos = np.clip(directions @ directions.T, -1.0, 1.0)
    return float(np.degrees(np.max(np.arccos(cos))))


def box_corners(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of the axis-aligned box between ``lower`` and ``upper``."""
    return np.array(np.meshgrid(*np.array([lower, upper], float).T, indexing="ij")).reshape(3, -1).T


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> Pose:
    """Pose ``T_world_cam`` of a camera at ``eye`` whose +z looks at ``target``.

    Image rows (+y) run along ``-up`` so that ``up`` appears at the top of the image.
    """
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    y = -(np.asarray(up, float) - np.dot(up, z) * z)
    if np.linalg.norm(y) < 1e-9:
        raise ValueError("look_at: 'up' is parallel to the viewing direction")
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return Pose(np.column_stack([x, y, z]), np.asarray(eye, float))
