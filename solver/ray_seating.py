"""Edge points seated on their observed rays, where each ray grazes its model: the depth a
contour pixel alone cannot say (docs/solver.md)."""

from __future__ import annotations

import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.kernels import ray_minima
from slamtka.solver.plan import RigidModel

__all__ = ["seat_on_rays"]

# Coarse ray search in seat_on_rays: steps this many times the fine step.
_SEAT_COARSE = 4
# Nearest depth searched (mm from the source).
_MIN_DEPTH_MM = 10.0


def seat_on_rays(
    model: RigidModel, T_cam_body: Pose, camera: Camera, pixels: np.ndarray, step_mm: float
) -> np.ndarray:
    """Body-frame 3D points on the rays of ``pixels`` where each ray grazes the model.

    Each ray's point is where the model's signed distance along it is least: the tangent
    point of a ray that grazes, the deepest point of one that just cuts in (so noise on
    either side of the outline is charged alike), the closest approach of one that misses.
    Each ray is searched where it crosses the distance field's box, at ``_SEAT_COARSE``
    steps, then at ``step_mm`` around the best, then refined to the vertex of a parabola
    (:func:`~slamtka.solver.kernels.ray_minima`: one compiled pass per ray, where numpy
    needed a dozen passes over every ray's samples).
    """
    rays = camera.rays(pixels)
    rays = rays / rays[:, 2:3]  # unit depth
    T_body_cam = T_cam_body.inverse()
    sdf = model.sdf
    # A model that went behind the source (a solve gone astray) still gets points, at the
    # nearest depth searched; the gates then refuse the solve.
    depth = ray_minima(sdf.values, np.asarray(sdf.origin, float), float(sdf.spacing),
                       np.ascontiguousarray(T_body_cam.R), T_body_cam.t, np.ascontiguousarray(rays),
                       _MIN_DEPTH_MM, float(step_mm), _SEAT_COARSE)
    return T_body_cam.apply(rays * depth[:, None])
