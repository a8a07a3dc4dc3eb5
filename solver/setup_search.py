"""Global initialisation: the patient set-up error, searched for once for all views.

The encoders tell how the C-arm moved between views far better than where the patient lies
(docs/solver.md): the large error of the initial guess is one rigid error of the
tibia, shared by every view. It can be tens of degrees, which no local method recovers, so
it is searched for exhaustively, with each view's image telling how well a hypothesis fits:

- the rotation about the knee centre (anatomical frame) runs over a grid of hypotheses; for
  each, the bone's outline (a decimated mesh) is projected into every view and slid over a
  truncated, reduced distance map of the observed contour for every image shift (one
  template correlation per view); at the best shift, the view's score is the mean distance
  of the best-placed 70% of the outline (its interior folds are never observed) plus the
  mean distance from the observed contour back to the outline (edges left unexplained);
- a hypothesis turns the bone about the knee centre and then carries the knee to where
  the views see it, so the knee stays put whatever the rotation; the best hypotheses'
  shifts say where the knee centre is seen in each view, and its rays, triangulated, place
  it again, depth (hence the outline's scale) included;
- coarse to fine: the coarse grid (most of the hypotheses) is first screened at half the
  resolution (a quarter of the correlation's cost), and only the hypotheses best there are
  scored at the search's resolution, which ranks them as before; on the study's cases the
  best ones were well within those passed on (docs/speed.md, "Global search"). The finer
  grids are not screened: there neighbours score alike, and the screening's ranking of
  them differed from the full one's. They look for image shifts of at most
  ``refine_search_px`` (a fifth of the window's area): the knee is placed by then, and
  turning the bone about it moves little of the outline's place.

The result is one correction ``C`` (tibia frame) with ``T_cam_k_tibia <- T_cam_k_tibia C``
for every view, so the motion between views is kept exactly as the encoders measured it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import product

import cv2
import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, so3_exp
from slamtka.solver.observations import DistanceMap
from slamtka.solver.silhouette import ContourGenerator
from slamtka.solver.triangulation import triangulate_rays

__all__ = ["SetupSearch", "search_setup"]

_FORWARD_KEPT = 0.7  # fraction of the outline (best placed) that scores a hypothesis


@dataclass(frozen=True)
class SetupSearch:
    """Extent and resolution of the search (angles in degrees about the anatomical axes)."""

    coarse_half_range_deg: float = 30.0
    coarse_step_deg: float = 15.0
    refinements: int = 2  # 3x3x3 grids around the best so far, each at half the step
    rescored: int = 8  # best coarse hypotheses scored again, the knee where their shifts put it
    search_px: int = 800  # largest image shift considered, full-resolution pixels
    truncate_px: float = 40.0
    spacing_px: float = 6.0
    downscale: int = 8
    screen_downscale: int = 16  # the coarse grid is screened at this coarser resolution first
    screened: int = 24  # coarse-grid hypotheses the screening passes on (>= rescored)
    refine_search_px: int = 200  # largest image shift in the refinements, the knee placed

    def __post_init__(self) -> None:
        if self.screened < self.rescored:
            raise ValueError("the screening must pass on at least the hypotheses rescored")
        if not 0 < self.refine_search_px <= self.search_px:
            raise ValueError("the refinements' shifts must lie within the search's")


class _ViewField:
    """One view's truncated distance map, reduced and padded for template correlation, and
    its observed contour pixels at the reduced resolution (for the reverse distance)."""

    def __init__(self, camera: Camera, distance_map: DistanceMap, observed: np.ndarray,
                 search: SetupSearch, downscale: int):
        self.camera, self.downscale = camera, downscale
        d = downscale
        self.shape = (-(-camera.height // d), -(-camera.width // d))
        reduced = np.unique(np.round(observed / d).astype(int), axis=0)
        self.observed = reduced[self._inside(reduced)]
        self.truncate = search.truncate_px / d
        self.reach = -(-search.search_px // d)
        field = distance_map.truncated(search.truncate_px)
        field = cv2.resize(field, None, fx=1 / d, fy=1 / d, interpolation=cv2.INTER_AREA) / d
        self.pad = 3 * self.reach
        self.padded = cv2.copyMakeBorder(field, self.pad, self.pad, self.pad, self.pad,
                                         cv2.BORDER_CONSTANT, value=self.truncate)

    def best_shift(self, uv: np.ndarray, search_px: int) -> tuple[float, np.ndarray]:
        """The view's score (reduced pixels) at the best image shift within ``search_px``
        (full-resolution pixels, at most the search's), and that shift in full-resolution
        pixels; an infinite score when the outline cannot be placed."""
        d = self.downscale
        reach = -(-search_px // d)
        scaled = uv / d
        origin = np.floor(scaled.min(axis=0)).astype(int)
        pix = np.round(scaled - origin).astype(int)
        size = pix.max(axis=0) + 1
        x0, y0 = origin + self.pad - reach
        window = self.padded[y0: y0 + 2 * reach + size[1], x0: x0 + 2 * reach + size[0]]
        if x0 < 0 or y0 < 0 or window.shape != (2 * reach + size[1], 2 * reach + size[0]):
            return np.inf, np.zeros(2)
        template = np.zeros((size[1], size[0]), np.float32)
        template[pix[:, 1], pix[:, 0]] = 1.0
        scores = cv2.matchTemplate(window, template, cv2.TM_CCORR)
        iy, ix = np.unravel_index(np.argmin(scores), scores.shape)
        shift = np.array([ix - reach, iy - reach])
        placed = pix + origin + shift
        # Interior folds of the outline (kept: tracing only the outer one costs more than the
        # whole correlation) are never observed, so the worst part of the outline is ignored.
        forward = self.padded[placed[:, 1] + self.pad, placed[:, 0] + self.pad]
        kept = np.sort(forward)[: max(1, int(_FORWARD_KEPT * len(forward)))]
        return float(np.mean(kept)) + self._reverse(placed), shift * float(d)

    def _reverse(self, outline: np.ndarray) -> float:
        """Mean truncated distance from the observed contour to the placed outline: an
        outline lying on some of the edges but leaving others unexplained scores badly."""
        image = np.full(self.shape, 255, np.uint8)
        inside = outline[self._inside(outline)]
        image[inside[:, 1], inside[:, 0]] = 0
        field = cv2.distanceTransform(image, cv2.DIST_L2, 3)
        obs = self.observed
        return float(np.mean(np.minimum(field[obs[:, 1], obs[:, 0]], self.truncate)))

    def _inside(self, pixels: np.ndarray) -> np.ndarray:
        """Mask of reduced-resolution pixels (N, 2) that lie inside the reduced image."""
        return np.all((pixels >= 0) & (pixels < np.array(self.shape[::-1])), axis=1)


def _rotations(half_range_deg: float, step_deg: float, centre: np.ndarray) -> list[np.ndarray]:
    """Rotation vectors (rad) on a cubic grid about ``centre``."""
    offsets = np.arange(-half_range_deg, half_range_deg + 1e-9, step_deg)
    return [centre + np.radians(np.array(o)) for o in product(offsets, repeat=3)]


class _Hypotheses:
    """Scores set-up hypotheses on every view. The views are scored in parallel threads:
    most of a view's cost is OpenCV's template correlation, which releases the GIL."""

    def __init__(self, contour: ContourGenerator,
                 views: list[tuple[Pose, Camera, DistanceMap, np.ndarray]],
                 T_tibia_anat: Pose, search: SetupSearch, pool: ThreadPoolExecutor):
        self.contour, self.views, self.search, self.pool = contour, views, search, pool
        self.T_tibia_anat, self.knee = T_tibia_anat, T_tibia_anat.t
        self.fields = {screening: [_ViewField(camera, dmap, observed, search, downscale)
                                   for _, camera, dmap, observed in views]
                       for screening, downscale in ((False, search.downscale),
                                                    (True, search.screen_downscale))}

    def correction(self, rotvec: np.ndarray, knee_at: np.ndarray) -> Pose:
        """The bone turned by ``rotvec`` (anatomical axes) about its knee centre, which is
        then carried to ``knee_at`` (frame of the initial guess)."""
        A = self.T_tibia_anat
        turned = A @ Pose(so3_exp(rotvec), np.zeros(3)) @ A.inverse()
        return Pose(np.eye(3), knee_at - self.knee) @ turned

    def _view_score(self, C: Pose, k: int, screening: bool,
                    search_px: int) -> tuple[float, np.ndarray]:
        (T, camera, _, _), search = self.views[k], self.search
        T_c = T @ C
        S = self.contour.outline_points(T_c, camera, search.spacing_px, outer_only=False,
                                        fov_margin_px=-float(search.search_px))
        if len(S) < 10:
            return np.inf, np.zeros(2)
        return self.fields[screening][k].best_shift(camera.project(T_c.apply(S)), search_px)

    def evaluate(self, rotvec: np.ndarray, knee_at: np.ndarray, screening: bool = False,
                 search_px: int | None = None) -> tuple[float, list[np.ndarray]]:
        """Summed view scores of a hypothesis and each view's best image shift (infinite,
        with no shifts, when the outline leaves some image); ``screening`` scores it at the
        screening resolution, ``search_px`` limits the shifts (default: the search's)."""
        C = self.correction(rotvec, knee_at)
        reach = self.search.search_px if search_px is None else search_px
        scored = list(self.pool.map(lambda k: self._view_score(C, k, screening, reach),
                                    range(len(self.views))))
        total = sum(score for score, _ in scored)
        return (total, [shift for _, shift in scored]) if np.isfinite(total) else (np.inf, [])

    def seen_at(self, pixels: list[np.ndarray]) -> np.ndarray:
        """The point (frame of the initial guess) the views see at ``pixels``, one each."""
        origins, directions = [], []
        for (T, camera, _, _), pixel in zip(self.views, pixels):
            T_tibia_cam = T.inverse()
            origins.append(T_tibia_cam.t)
            directions.append(T_tibia_cam.rotate(camera.rays(pixel[None])[0]))
        return triangulate_rays(np.array(origins), np.array(directions))[0]

    def shifted(self, knee_at: np.ndarray, shifts: list[np.ndarray]) -> np.ndarray:
        """The knee moved by each view's best image shift."""
        return self.seen_at([camera.project(T.apply(knee_at[None]))[0] + shift
                             for (T, camera, _, _), shift in zip(self.views, shifts)])

    def screened(self, rotvecs: list[np.ndarray], knee_at: np.ndarray,
                 kept: int) -> list[tuple[float, list[np.ndarray], np.ndarray]]:
        """Score, shifts and rotation of the ``kept`` hypotheses best at the screening
        resolution, scored at the search's, in grid order (as an exhaustive scoring would
        meet them, so that ties go the same way)."""
        rough = [self.evaluate(rotvec, knee_at, screening=True)[0] for rotvec in rotvecs]
        passed = np.sort(np.argsort(rough, kind="stable")[:kept])
        return [(*self.evaluate(rotvecs[i], knee_at), rotvecs[i]) for i in passed]


def search_setup(
    contour: ContourGenerator,
    views: list[tuple[Pose, Camera, DistanceMap, np.ndarray]],
    T_tibia_anat: Pose,
    search: SetupSearch = SetupSearch(),
) -> Pose:
    """The correction ``C`` (tibia frame) that best overlays the bone on every view;
    ``views`` holds each view's initial pose, camera, bone distance map and bone contour."""
    with ThreadPoolExecutor(len(views)) as pool:
        h = _Hypotheses(contour, views, T_tibia_anat, search, pool)
        # The knee first where the contours are (the C-arm is aimed at it; the guess may be
        # far enough off to leave the bone out of the image), then where the views' best
        # shifts put it (a wrong depth scales the outline, which no rotation explains), then
        # the rotation on a coarse grid and finer ones, the knee placed again after each.
        knee_at = h.seen_at([observed.mean(axis=0) for *_, observed in views])
        score, shifts = h.evaluate(np.zeros(3), knee_at)
        if not np.isfinite(score):
            return Pose.identity()
        knee_at = h.shifted(knee_at, shifts)
        # Coarse grid: every hypothesis screened, and the best scored, with the knee where no
        # rotation put it, which a rotation tens of degrees away sees at a somewhat wrong
        # place and depth; the best few are scored again with the knee where their own image
        # shifts put it.
        coarse = sorted(h.screened(_rotations(search.coarse_half_range_deg, search.coarse_step_deg,
                                              np.zeros(3)), knee_at, search.screened),
                        key=lambda hypothesis: hypothesis[0])
        best: tuple[float, np.ndarray, np.ndarray] = (np.inf, np.zeros(3), knee_at)
        for score, shifts, rotvec in coarse[: search.rescored]:
            own = knee_at
            for _ in range(2):
                if not np.isfinite(score):  # the outline left some image
                    break
                own = h.shifted(own, shifts)
                score, shifts = h.evaluate(rotvec, own)
            if score < best[0]:
                best = (score, rotvec, own)
        _, best_rotvec, knee_at = best
        for half in [search.coarse_step_deg / 2**i for i in range(1, search.refinements + 1)]:
            fine: tuple[float, np.ndarray, list[np.ndarray]] = (np.inf, best_rotvec, [])
            for rotvec in _rotations(half, half, best_rotvec):
                score, shifts = h.evaluate(rotvec, knee_at, search_px=search.refine_search_px)
                if score < fine[0]:
                    fine = (score, rotvec, shifts)
            score, best_rotvec, shifts = fine
            if not np.isfinite(score):
                break
            knee_at = h.shifted(knee_at, shifts)
        return h.correction(best_rotvec, knee_at)
