"""Edge points seated on their observed rays, where each ray grazes its model: the depth a
contour pixel alone cannot say (docs/solver.md)."""

from __future__ import annotations

import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.plan import RigidModel

__all__ = ["seat_on_rays"]

# Coarse ray search in seat_on_rays: steps this many times the fine step.
_SEAT_COARSE = 4


def _ray_depths_in_box(rays: np.ndarray, T_body_cam: Pose, box: np.ndarray) -> np.ndarray:
    """Depth interval (N, 2) in which each camera ray ``z * ray`` (unit-depth rays) crosses the
    body-frame box ``box`` (2, 3) (slab test). A ray that misses the box gets the empty
    interval at its closest approach to the box's centre."""
    origin = T_body_cam.t
    direction = rays @ T_body_cam.R.T  # body-frame direction per unit depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - origin) / direction
        t1 = (box[1] - origin) / direction
    # An axis the ray runs parallel to constrains nothing if the source lies within its slab.
    parallel = direction == 0
    inside = (origin >= box[0]) & (origin <= box[1])
    t0 = np.where(parallel, np.where(inside, -np.inf, np.inf), t0)
    t1 = np.where(parallel, np.where(inside, np.inf, -np.inf), t1)
    near = np.max(np.minimum(t0, t1), axis=1)
    far = np.min(np.maximum(t0, t1), axis=1)
    missed = ~(far >= near)
    if np.any(missed):
        centre = box.mean(axis=0) - origin
        closest = direction[missed] @ centre / np.sum(direction[missed] ** 2, axis=1)
        near[missed] = far[missed] = closest
    return np.column_stack([near, far])


def seat_on_rays(
    model: RigidModel, T_cam_body: Pose, camera: Camera, pixels: np.ndarray, step_mm: float
) -> np.ndarray:
    """Body-frame 3D points on the rays of ``pixels`` where each ray grazes the model.

    Each ray's point is where the model's signed distance along it is least: the tangent
    point of a ray that grazes, the deepest point of one that just cuts in (so noise on
    either side of the outline is charged alike), the closest approach of one that misses.
    Each ray is searched where it crosses the distance field's box, at ``_SEAT_COARSE``
    steps, then at ``step_mm`` around the best, then refined to the vertex of a parabola.
    """
    rays = camera.rays(pixels)
    rays = rays / rays[:, 2:3]  # unit depth
    T_body_cam = T_cam_body.inverse()
    # A model that went behind the source (a solve gone astray) still gets points, at the
    # nearest depth searched; the gates then refuse the solve.
    depths = np.maximum(_ray_depths_in_box(rays, T_body_cam, model.sdf.bounds()), 10.0)

    def distances(z: np.ndarray) -> np.ndarray:
        """Signed distances (rays, samples) at depths ``z`` (rays, samples)."""
        samples = (rays[:, None, :] * z[:, :, None]).reshape(-1, 3)
        return model.sdf.query(T_body_cam.apply(samples), gradient=False)[0].reshape(z.shape)

    coarse_step = _SEAT_COARSE * step_mm
    samples = int(np.ceil(np.max(depths[:, 1] - depths[:, 0]) / coarse_step)) + 1
    z = np.minimum(depths[:, :1] + coarse_step * np.arange(samples), depths[:, 1:])
    rows = np.arange(len(pixels))
    around = z[rows, np.argmin(distances(z), axis=1)]
    offsets = np.arange(-_SEAT_COARSE, _SEAT_COARSE + 1) * step_mm
    z_fine = around[:, None] + offsets[None, :]
    d = distances(z_fine)
    best = np.clip(np.argmin(d, axis=1), 1, len(offsets) - 2)
    # Near a grazing point the distance along the ray is a parabola: refine to its vertex.
    d_minus, d_0, d_plus = d[rows, best - 1], d[rows, best], d[rows, best + 1]
    curvature = d_plus - 2.0 * d_0 + d_minus
    shift = np.where(curvature > 1e-9, 0.5 * (d_minus - d_plus) / np.maximum(curvature, 1e-9), 0.0)
    depth = z_fine[rows, best] + np.clip(shift, -1.0, 1.0) * step_mm
    return T_body_cam.apply(rays * depth[:, None])

