"""Global initialisation of a view: where in the image is the bone?

The encoder guess can leave the bone a few hundred pixels from where it is seen (20 mm of
set-up error is ~150 px at the detector). Gauss-Newton on silhouettes cannot bridge that, so
each view is first aligned exhaustively in the image: the projected model silhouette is slid
over a truncated distance map of the observed contour for every image shift (one template
correlation) and a few in-plane rotations, and the best placement becomes a rotation of the
camera about its source. Cost: a few milliseconds per view.
"""

from __future__ import annotations

import cv2
import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, rotation_about
from slamtka.solver.observations import DistanceMap
from slamtka.solver.silhouette import ContourGenerator

__all__ = ["align_view_in_image"]


def align_view_in_image(
    contour: ContourGenerator,
    T_cam_model: Pose,
    camera: Camera,
    distance_map: DistanceMap,
    search_px: int = 400,
    truncate_px: float = 30.0,
    angles_deg: tuple[float, ...] = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0, 12.0),
    spacing_px: float = 4.0,
    downscale: int = 4,
) -> Pose:
    """``T_cam_model`` corrected by the camera rotation that best overlays the silhouette.

    The search runs on images reduced ``downscale`` times (the later Gauss-Newton stages
    absorb the remaining pixel or two), which makes it cheap enough to try every shift."""
    S = contour.outline_points(T_cam_model, camera, spacing_px, outer_only=True,
                               fov_margin_px=-float(search_px))
    if len(S) < 10:
        return T_cam_model
    uv = camera.project(T_cam_model.apply(S)) / downscale
    centre = np.array([camera.cx, camera.cy]) / downscale
    truncate_px /= downscale
    search_px = -(-search_px // downscale)
    field = distance_map.truncated(truncate_px * downscale)
    field = cv2.resize(field, None, fx=1 / downscale, fy=1 / downscale,
                       interpolation=cv2.INTER_AREA) / downscale
    pad = 3 * search_px
    padded = cv2.copyMakeBorder(field, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=truncate_px)
    best = (np.inf, 0.0, np.zeros(2))
    for angle in angles_deg:
        c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        rotated = (uv - centre) @ np.array([[c, s], [-s, c]]) + centre
        origin = np.floor(rotated.min(axis=0)).astype(int)
        pix = np.round(rotated - origin).astype(int)
        size = pix.max(axis=0) + 1
        template = np.zeros((size[1], size[0]), np.float32)
        template[pix[:, 1], pix[:, 0]] = 1.0
        # With image shift d the template's top-left sits at padded position origin + pad + d.
        x0, y0 = origin + pad - search_px
        window = padded[y0: y0 + 2 * search_px + size[1], x0: x0 + 2 * search_px + size[0]]
        if x0 < 0 or y0 < 0 or window.shape != (2 * search_px + size[1], 2 * search_px + size[0]):
            continue
        scores = cv2.matchTemplate(window, template, cv2.TM_CCORR)
        iy, ix = np.unravel_index(np.argmin(scores), scores.shape)
        score = scores[iy, ix] / len(pix)
        if score < best[0]:
            best = (score, angle, np.array([ix - search_px, iy - search_px], float))
    _, angle, shift = best
    shift = shift * downscale
    # In-plane rotation about the optical axis, then the rotation that moves the image by
    # ``shift``: rotating camera-frame points about y moves them along u, about x along v.
    x, y, z = np.eye(3)
    R = (rotation_about(x, -np.arctan2(shift[1], camera.fy))
         @ rotation_about(y, np.arctan2(shift[0], camera.fx))
         @ rotation_about(z, np.radians(angle)))
    return Pose(R, np.zeros(3)) @ T_cam_model
