"""C-arm calibration from ball-plate phantom images (the file it writes:
:mod:`slamtka.solver.imaging.calibration_file`).

Estimation (:func:`calibrate`), made for real sets (issue 29):

1. Screening: frames of another size or pixel spacing than the set's, and byte copies of an
   earlier frame, are set aside by name.
2. Each frame's balls and their grid (:mod:`solver.imaging.ballgrid`): a frame without the
   phantom, or whose grid cannot be found, is set aside with the reason; a speck or a
   missing ball costs that ball, not the frame.
3. A first guess (OpenCV, one focal length, principal point at the field's centre, no
   distortion), then a robust bundle adjustment (:mod:`solver.imaging.bundle`) of the focal
   length, principal point, intensifier distortion and every plate pose, the plate taken as
   perfect; balls far off the fit are outliers, removed and reported.
4. The plate's own error: the frames are placed on one physical labelling of the balls (a
   frame alone knows its grid only up to the square's symmetries; the placement that fits
   the plate seen so far is chosen), then the ball offsets are estimated jointly with
   everything else. The pitch is only a scale: it changes no intrinsic.
5. Frames that still do not fit the others (RMS far above the median) are set aside by name.

Guards: the focal lengths are tied (square pixels, or the detector's aspect), the principal
point is bounded to ``max_principal_offset_px`` of the field's centre and held there (and
reported so) when the set cannot determine it (standard error above
``max_principal_sigma_px``); a focal length far from the nominal ``SID / pixel spacing`` is
refused, as are sets with too few usable frames, all plates nearly fronto-parallel, or a
final RMS above ``max_rms_px``. Every run produces a report (:func:`calibrate` returns it;
a refusal carries it on the :class:`CalibrationError`).
"""

from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slamtka.solver.camera import Camera
from slamtka.solver.imaging import bundle
from slamtka.solver.imaging.ballgrid import GridError, detect_balls, match_grid, placements
from slamtka.solver.imaging.calibration_file import Calibration, CalibrationError, calibration_document
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.imaging.field import FieldError, field_of_view
from slamtka.solver.imaging.plate import PhantomSpec

__all__ = ["CalibrationOptions", "CalibrationImage", "calibrate", "REPORT_FORMAT"]

REPORT_FORMAT = "slamtka-calibration-report/1"
_PLACE_SIGMAS = 3.0  # a ball further off a placement's fit (in noise SDs) counts as this far
_MIN_PLACE_CAP_PX = 0.05
_RELABEL_ROUNDS = 3
_RAY_PRIOR = 1e-3  # pull of the grid on a ball triangulated from rays (per ray: 1)
_REASSOCIATE_PX = 2.0  # a blob this close to a ball's projection is that ball


@dataclass(frozen=True)
class CalibrationOptions:
    min_images: int = 6
    min_balls: int = 12
    min_max_tilt_deg: float = 10.0  # some plate must be tilted at least this much
    max_principal_offset_px: float = 60.0  # principal point bound around the field centre
    max_principal_sigma_px: float = 8.0  # beyond: the set cannot fix it, hold it at the centre
    max_focal_deviation: float = 0.15  # from SID / pixel spacing, when both are known
    max_rms_px: float = 1.0
    refine_plate: bool = True  # estimate the balls' offsets from the perfect grid
    outlier_sigmas: float = 5.0  # a ball this many noise SDs off the fit is an outlier ...
    min_outlier_px: float = 0.2  # ... and at least this far
    misfit_factor: float = 4.0  # a frame whose RMS is this many times the median is set aside ...
    min_misfit_px: float = 0.5
    max_outlier_share: float = 0.3  # ... as is one with more of its balls off the fit


@dataclass
class CalibrationImage:
    """One phantom frame as handed to :func:`calibrate`."""

    name: str
    pixels: np.ndarray
    pixel_spacing_mm: tuple[float, float] | None = None
    sid_mm: float | None = None
    field_mm: float | None = None  # intensifier / detector field size, when the frame says


@dataclass
class _Frame:
    """A frame whose grid was found, through the estimation."""

    image: CalibrationImage
    uv: np.ndarray  # (K, 2) ball centres, px
    grid: np.ndarray  # (K, 2) the frame's own grid coordinates
    ball: np.ndarray  # (K,) plate ball index under the current placement
    pose: np.ndarray  # (6,) rotation vector, translation (mm): T_cam_plate
    active: np.ndarray  # (K,) not an outlier
    tilt_deg: float = 0.0


class _Run:
    """The report of one calibration run, filled in as the run goes."""

    def __init__(self, images: list[CalibrationImage], spec: PhantomSpec, calibration_id: str):
        self.doc: dict = {"format": REPORT_FORMAT, "calibration_id": calibration_id,
                          "created": datetime.now(UTC).isoformat(timespec="seconds"),
                          "status": "running", "refusal": None, "phantom": spec.to_json(),
                          "images": []}
        self.entries: dict[str, dict] = {}
        for im in images:
            entry = {"image": im.name, "used": False, "reason": None, "balls_found": None,
                     "balls_used": 0, "stray_blobs": 0, "outlier_balls": [], "rms_px": None,
                     "tilt_deg": None}
            self.entries.setdefault(im.name, entry)
            self.doc["images"].append(entry)

    def set_aside(self, name: str, reason: str) -> None:
        self.entries[name].update(used=False, reason=reason)

    def refuse(self, message: str) -> CalibrationError:
        self.doc.update(status="refused", refusal=message)
        return CalibrationError(message, self.doc)


def _screen(images: list[CalibrationImage], run: _Run) -> list[CalibrationImage]:
    """The frames of the set's size and spacing, each once; the rest set aside by name."""
    shape = Counter(im.pixels.shape for im in images).most_common(1)[0][0]
    spacings = Counter(im.pixel_spacing_mm for im in images if im.pixel_spacing_mm is not None)
    spacing = spacings.most_common(1)[0][0] if spacings else None
    seen: dict[str, str] = {}
    kept = []
    for im in images:
        digest = hashlib.sha256(np.ascontiguousarray(im.pixels).tobytes()).hexdigest()
        if im.pixels.shape != shape:
            run.set_aside(im.name, f"different size {im.pixels.shape[1]}x{im.pixels.shape[0]} px "
                                   f"from the set's {shape[1]}x{shape[0]} px")
        elif im.pixel_spacing_mm is not None and spacing is not None and im.pixel_spacing_mm != spacing:
            run.set_aside(im.name, f"different pixel spacing {list(im.pixel_spacing_mm)} mm from "
                                   f"the set's {list(spacing)} mm")
        elif digest in seen:
            run.set_aside(im.name, f"duplicate: the same pixels as {seen[digest]}")
        else:
            seen[digest] = im.name
            kept.append(im)
    return kept


def _find_grids(images: list[CalibrationImage], spec: PhantomSpec, options: CalibrationOptions,
                run: _Run) -> list[tuple[_Frame, np.ndarray, float | None]]:
    """Frames whose grid was found, with their field's centre and radius."""
    found = []
    for im in images:
        entry = run.entries[im.name]
        try:
            centre, radius = field_of_view(im.pixels, "auto", "phantom")[:2]
            balls = detect_balls(im.pixels)
            entry["balls_found"] = len(balls)
            if len(balls) < 4:
                raise GridError(f"no phantom in the image ({len(balls)} ball-like blobs)")
            index, grid = match_grid(balls, spec.rows, spec.cols, options.min_balls)
        except (GridError, FieldError) as exc:
            run.set_aside(im.name, str(exc))
            continue
        entry["stray_blobs"] = len(balls) - len(index)
        ball = placements(grid, spec.rows, spec.cols)[0][0]
        found.append((_Frame(im, balls[index], grid, ball, np.zeros(6), np.ones(len(index), bool)),
                      centre, radius))
    return found


def _observations(frames: list[_Frame]) -> bundle.Observations:
    return bundle.Observations(np.concatenate([np.full(len(f.uv), k) for k, f in enumerate(frames)]),
                               np.concatenate([f.ball for f in frames]),
                               np.concatenate([f.uv for f in frames]),
                               np.concatenate([f.active & (f.ball >= 0) for f in frames]))


def _store(frames: list[_Frame], model: bundle.Bundle, x: np.ndarray, obs: bundle.Observations) -> None:
    """Write the solved poses and outlier flags back into the frames."""
    poses = x[bundle.N_INTRINSIC: bundle.N_INTRINSIC + 6 * len(frames)].reshape(-1, 6)
    for k, f in enumerate(frames):
        f.pose = poses[k].copy()
        f.active = obs.active[obs.frame == k] | (f.ball < 0)  # beyond the plate is no outlier


class _Estimator:
    """The bundle adjustment of a set of frames, with outliers removed between solves."""

    def __init__(self, spec: PhantomSpec, options: CalibrationOptions, base: Distortion,
                 aspect: float, centre: np.ndarray):
        self.spec, self.options, self.base, self.aspect, self.centre = spec, options, base, aspect, centre
        self.nominal = spec.points()
        self.basis = bundle.plate_basis(self.nominal) if options.refine_plate else None
        self.plate_x = None if self.basis is None else np.zeros(self.basis.shape[1])
        self.intrinsics = np.zeros(bundle.N_INTRINSIC)
        self.sigma = 1.0  # the fit's noise SD per axis (px), as last estimated

    def model(self, frames: list[_Frame], plate: bool) -> tuple[bundle.Bundle, np.ndarray]:
        m = bundle.Bundle(self.nominal, self.basis if plate else None, self.base, self.aspect, len(frames))
        x = np.concatenate([self.intrinsics, *[f.pose for f in frames],
                            self.plate_x if plate and self.plate_x is not None else []])
        return m, x

    def bounds(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        off = self.options.max_principal_offset_px
        lower, upper = np.full(len(x), -np.inf), np.full(len(x), np.inf)
        c = self.centre
        lower[:7] = [0.2 * x[0], c[0] - off, c[1] - off, -0.5, -0.5, -0.2, -0.2]
        upper[:7] = [5.0 * x[0], c[0] + off, c[1] + off, 0.5, 0.5, 0.2, 0.2]
        return lower, upper

    def fit(self, frames: list[_Frame], plate: bool, hold_principal: bool = False,
            robust: bool = True) -> tuple[bundle.Bundle, np.ndarray, object, bundle.Observations]:
        """Solve, flag outliers (all observations judged afresh), solve again until stable."""
        m, x = self.model(frames, plate)
        if hold_principal:
            x[1:3] = self.centre
        free = np.ones(len(x), bool)
        free[1:3] = not hold_principal
        obs = _observations(frames)
        lower, upper = self.bounds(x)
        for _ in range(4):
            x, result = bundle.solve(m, x, obs, lower, upper, free, 1.0 if robust else None)
            r = bundle.ball_residuals(m, x, obs)
            sigma = float(np.median(r[obs.active])) / 1.1774  # Rayleigh median -> SD per axis
            self.sigma = sigma
            active = (r <= max(self.options.outlier_sigmas * sigma, self.options.min_outlier_px)) & (obs.ball >= 0)
            if np.array_equal(active, obs.active):
                break
            obs.active = active
        self.intrinsics = x[: bundle.N_INTRINSIC].copy()
        if plate:
            self.plate_x = x[bundle.N_INTRINSIC + 6 * len(frames):].copy()
        _store(frames, m, x, obs)
        return m, x, result, obs

    # -- the plate's physical labelling ---------------------------------------------------
    def _camera(self) -> tuple[np.ndarray, Distortion]:
        f, cx, cy = self.intrinsics[:3]
        K = np.array([[f, 0, cx], [0, f * self.aspect, cy], [0, 0, 1]])
        return K, self.base.with_params(self.intrinsics[3:7])

    def _plate(self) -> np.ndarray:
        if self.basis is None or self.plate_x is None:
            return self.nominal
        return self.nominal + (self.basis @ self.plate_x).reshape(-1, 3)

    def _place(self, frame: _Frame, plate: np.ndarray) -> None:
        """Put the frame on the placement of its grid that fits ``plate`` best (pose with it).

        The score is a squared error over the frame's balls truncated at a few noise SDs (a
        point beyond the plate, or far off, costs the truncation), so a speck continuing the
        lattice does not pull the placement by a step."""
        K, distortion = self._camera()
        cap = max(_PLACE_SIGMAS * self.sigma, _MIN_PLACE_CAP_PX) ** 2
        ideal = distortion.undistort(frame.uv).astype(np.float64)
        best = None
        for ball, _, _ in placements(frame.grid, self.spec.rows, self.spec.cols):
            use = frame.active & (ball >= 0)
            for _ in range(2):  # solve, then again without the points far off
                if use.sum() < 6:
                    break
                ok, rvec, tvec = cv2.solvePnP(plate[ball[use]], ideal[use], K, None,
                                              flags=cv2.SOLVEPNP_ITERATIVE)
                if not ok or tvec[2, 0] <= 0:
                    break
                projected = cv2.projectPoints(plate[np.maximum(ball, 0)], rvec, tvec, K, None)[0]
                r2 = np.where(ball >= 0, np.sum((projected.reshape(-1, 2) - ideal) ** 2, axis=1), np.inf)
                use = frame.active & (r2 < max(4.0 * cap, 1.0))  # far off: a speck, say
            else:
                score = float(np.sum(np.minimum(r2[frame.active], cap)))
                if best is None or score < best[0]:
                    best = score, ball, np.concatenate([rvec.ravel(), tvec.ravel()])
        if best is not None:
            frame.ball, frame.pose = best[1], best[2]

    def _offsets(self, frames: list[_Frame]) -> np.ndarray:
        """Plate coefficients from the frames' rays: each ball is the point nearest to all
        rays through it (in the plate frame), pulled weakly towards the grid so that a ball
        seen in one frame only stays on the plate (its z needs two tilts)."""
        assert self.basis is not None, "plate offsets are estimated only with refine_plate"
        K, distortion = self._camera()
        n = len(self.nominal)
        A, b = np.zeros((n, 3, 3)), np.zeros((n, 3))
        for f in frames:
            a = f.active & (f.ball >= 0)
            ideal = distortion.undistort(f.uv[a])
            rays = np.column_stack([ideal, np.ones(len(ideal))]) @ np.linalg.inv(K).T
            R = bundle.rotations(f.pose[None, :3])[0]
            origin, d = -R.T @ f.pose[3:], rays @ R  # plate frame
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            P = np.eye(3) - d[:, :, None] * d[:, None, :]  # projectors across each ray
            np.add.at(A, f.ball[a], P)
            np.add.at(b, f.ball[a], P @ origin)
        weight = _RAY_PRIOR * np.eye(3)
        balls = np.linalg.solve(A + weight, (b + self.nominal @ weight)[..., None])[..., 0]
        return self.basis.T @ (balls - self.nominal).ravel()

    def label(self, frames: list[_Frame]) -> None:
        """One physical labelling: the frame with most balls is the reference; each further
        frame takes the placement that fits the plate estimated from those before it."""
        order = sorted(range(len(frames)), key=lambda k: -int(frames[k].active.sum()))
        placed = [frames[order[0]]]
        self.plate_x = self._offsets(placed)
        for k in order[1:]:
            self._place(frames[k], self._plate())
            placed.append(frames[k])
            self.plate_x = self._offsets(placed)

    def reassociate(self, frame: _Frame) -> bool:
        """Name a misfitting frame's balls afresh from the camera fitted to the others.

        A lattice matched wrongly in part (a steeply tilted plate at the field's rim, a speck
        taken into it) gives balls wrong names, which no placement undoes. The balls whose
        names agree still give the pose (RANSAC over each placement); every blob is then the
        ball whose projection it lies on. Whether at least ``min_balls`` balls were named."""
        K, distortion = self._camera()
        plate = self._plate()
        ideal = distortion.undistort(frame.uv).astype(np.float64)
        best: tuple[int, np.ndarray, np.ndarray] | None = None
        for ball, _, _ in placements(frame.grid, self.spec.rows, self.spec.cols):
            on = ball >= 0
            if on.sum() < 6:
                continue
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(plate[ball[on]], ideal[on], K, None,
                                                         reprojectionError=_REASSOCIATE_PX,
                                                         iterationsCount=100)
            if not ok or inliers is None or len(inliers) < 6 or tvec[2, 0] <= 0:
                continue
            projected = cv2.projectPoints(plate, rvec, tvec, K, None)[0].reshape(-1, 2)
            distance, nearest = cKDTree(projected).query(ideal)
            named = np.where(distance < _REASSOCIATE_PX, nearest, -1)
            # Two blobs on one ball (a speck beside it): the nearer is the ball.
            order = np.argsort(distance)
            first = np.zeros(len(named), bool)
            first[order[np.unique(named[order], return_index=True)[1]]] = True
            named = np.where(first, named, -1)
            count = int(np.sum(named >= 0))
            if best is None or count > best[0]:
                best = count, named, np.concatenate([rvec.ravel(), tvec.ravel()])
        if best is None or best[0] < self.options.min_balls:
            return False
        frame.ball, frame.pose = best[1], best[2]
        frame.active = frame.ball >= 0
        return True

    def relabel(self, frames: list[_Frame]) -> bool:
        """Check every frame's placement against the refined plate; whether any changed."""
        changed = False
        plate = self._plate()
        for f in frames:
            before = f.ball.copy()
            self._place(f, plate)
            changed |= not np.array_equal(before, f.ball)
        return changed


def calibrate(images: list[CalibrationImage], spec: PhantomSpec = PhantomSpec(),
              options: CalibrationOptions = CalibrationOptions(), calibration_id: str = "carm",
              description: str = "", device: dict[str, str] | None = None) -> tuple[Calibration, dict]:
    """Estimate a :class:`Calibration` from phantom frames; also returns the run's report.

    ``device``: the identity of the C-arm the frames came from (e.g. its Device Serial
    Number), stored in the file so that the service picks the calibration for its frames.

    Frames that cannot be used are set aside by name in the report (and the file); a set
    that cannot determine the camera raises :class:`CalibrationError` carrying the report.
    """
    run = _Run(images, spec, calibration_id)
    if not images:
        raise run.refuse("no calibration images given")
    found = _find_grids(_screen(images, run), spec, options, run)
    frames = [f for f, _, _ in found]
    if len(frames) < options.min_images:
        aside = "; ".join(f"{e['image']}: {e['reason']}" for e in run.doc["images"] if e["reason"])
        raise run.refuse(f"only {len(frames)} usable images, need {options.min_images} "
                         f"(set aside: {aside or 'none'})")
    height, width = frames[0].image.pixels.shape
    spacing = next((f.image.pixel_spacing_mm for f in frames if f.image.pixel_spacing_mm), None)
    aspect = 1.0 if spacing is None else spacing[1] / spacing[0]  # fy / fx = col / row spacing
    centre = np.median([c for _, c, _ in found], axis=0)
    radii = [r for _, _, r in found if r is not None]
    radius = float(np.median(radii)) if radii else None
    base = Distortion(float(centre[0]), float(centre[1]), radius or max(width, height) / 2.0)
    sids = [f.image.sid_mm for f in frames if f.image.sid_mm]
    nominal_f = float(np.median(sids)) / spacing[1] if spacing is not None and sids else None

    estimator = _Estimator(spec, options, base, aspect, centre)
    _first_guess(frames, estimator, nominal_f or 4.0 * max(width, height), (width, height))
    largest = max(f.tilt_deg for f in frames)
    if largest < options.min_max_tilt_deg:
        raise run.refuse(f"all plates are nearly fronto-parallel (largest tilt {largest:.1f} deg, "
                         f"need {options.min_max_tilt_deg}); tilt the phantom")
    try:
        frames, (m, x, result, obs) = _estimate(frames, estimator, options, run)
        sigmas = _sigmas(result, obs)
        pp_sigma = float(max(sigmas[1], sigmas[2]))
        held = pp_sigma > options.max_principal_sigma_px
        if held:
            m, x, result, obs = estimator.fit(frames, options.refine_plate, hold_principal=True, robust=False)
            sigmas = _sigmas(result, obs, held=True)
        distortion = base.with_params(x[3:7])
    except ValueError as exc:  # Distortion refuses a map that folds the image
        raise run.refuse(f"the fitted distortion is not physical ({exc}): the frames do not determine "
                         "it; add frames with the plate out to the field's rim") from None
    _fill_report(run, frames, m, x, obs, spec)
    rms = float(np.sqrt(np.mean(bundle.ball_residuals(m, x, obs)[obs.active] ** 2)))
    f, cx, cy = (float(v) for v in x[:3])
    names = ("f_px", "cx_px", "cy_px", "k1", "k2", "t1_rad", "t2_rad")
    run.doc.update(
        rms_px=rms, used=len(frames), observations=int(obs.active.sum()),
        parameters=int(len(x) - 2 * held),
        intrinsics={n: {"value": float(v), "sd": float(s)} for n, v, s in zip(names, x[:7], sigmas)},
        principal_point={"held_at_field_centre": held, "sigma_px": pp_sigma,
                         "why": (f"the set does not determine it (standard error {pp_sigma:.1f} px > "
                                 f"{options.max_principal_sigma_px} px): held at the field centre")
                         if held else "estimated"},
        plate=_plate_report(m, x, obs))
    if nominal_f is not None and abs(f / nominal_f - 1.0) > options.max_focal_deviation:
        raise run.refuse(f"estimated focal length {f:.0f} px is {100 * (f / nominal_f - 1):+.0f}% from "
                         f"the nominal SID / pixel spacing {nominal_f:.0f} px: implausible")
    if rms > options.max_rms_px:
        worst = sorted((e for e in run.doc["images"] if e["used"]), key=lambda e: -e["rms_px"])[:3]
        raise run.refuse(f"calibration RMS {rms:.2f} px exceeds {options.max_rms_px} px; the images "
                         "that fit worst: " + ", ".join(f"{e['image']} (RMS {e['rms_px']:.2f} px, "
                                                        f"{len(e['outlier_balls'])} outlier balls)"
                                                        for e in worst))
    run.doc["status"] = "calibrated"
    camera = Camera(f, f * aspect, cx, cy, width, height, radius)
    fields = {f.image.field_mm for f in frames}
    doc = calibration_document(camera, calibration_id, description or "C-arm calibration from phantom",
                               distortion, spacing, _file_extra(run.doc, spec, device),
                               field_mm=fields.pop() if len(fields) == 1 else None)
    report = {**run.doc, "rejected": doc["rejected"], "principal_held": held, "principal_sigma_px": pp_sigma}
    return Calibration(camera, distortion, calibration_id, doc["sha256"], spacing, doc), report


def _first_guess(frames: list[_Frame], estimator: _Estimator, focal: float, size: tuple[int, int]) -> None:
    """Plate poses and a focal length from OpenCV (principal point at the field centre, no
    distortion, the plate taken as perfect); each frame's tilt."""
    plate = estimator.nominal
    c = estimator.centre
    K0 = np.array([[focal, 0, c[0]], [0, focal * estimator.aspect, c[1]], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    _, K1, _, rvecs, tvecs = cv2.calibrateCamera(
        [plate[f.ball].astype(np.float32) for f in frames], [f.uv.astype(np.float32) for f in frames],
        size, K0, np.zeros(5), flags=flags)
    for f, r, t in zip(frames, rvecs, tvecs):
        f.pose = np.concatenate([r.ravel(), t.ravel()])
        f.tilt_deg = float(np.degrees(np.arccos(abs(cv2.Rodrigues(r)[0][2, 2]))))
    estimator.intrinsics = np.array([K1[0, 0], c[0], c[1], 0.0, 0.0, 0.0, 0.0])


def _estimate(frames: list[_Frame], estimator: _Estimator, options: CalibrationOptions, run: _Run):
    """The robust fit (plate as perfect, then the plate's own error with one physical
    labelling), repeated without the frames that do not fit the others; returns the frames
    used and the final (model, parameters, scipy result, observations)."""
    reassociated: set[str] = set()
    while True:
        estimator.fit(frames, plate=False)
        if options.refine_plate:
            estimator.label(frames)
            estimator.fit(frames, plate=True)
            for _ in range(_RELABEL_ROUNDS):  # placements checked against the refined plate
                if not estimator.relabel(frames):
                    break
                estimator.fit(frames, plate=True)
        m, x, result, obs = estimator.fit(frames, options.refine_plate, robust=False)
        errors = [_rms(m, x, obs, k) for k in range(len(frames))]
        median = float(np.median(errors))
        limit = max(options.min_misfit_px, options.misfit_factor * median)
        on_plate = [(obs.frame == k) & (obs.ball >= 0) for k in range(len(frames))]
        off = [int(np.sum(mine & ~obs.active)) for mine in on_plate]
        misfits = [k for k, e in enumerate(errors)
                   if e > limit or off[k] > options.max_outlier_share * on_plate[k].sum()]
        if not misfits or len(frames) - len(misfits) < options.min_images:
            return frames, (m, x, result, obs)
        # Once per frame: its balls named afresh from the others' camera, and the fit again.
        retry = [k for k in misfits if frames[k].image.name not in reassociated]
        reassociated.update(frames[k].image.name for k in retry)
        if sum([estimator.reassociate(frames[k]) for k in retry]):
            continue
        for k in misfits:
            run.set_aside(frames[k].image.name, f"does not fit the other images ({off[k]} of "
                          f"{on_plate[k].sum()} balls off the fit, RMS "
                          f"{_rms(m, x, obs, k, outliers=True):.2f} px against their median "
                          f"{median:.2f} px): the plate moved during the exposure, or the frame is "
                          "from another C-arm or setting")
        frames = [f for k, f in enumerate(frames) if k not in misfits]


def _file_extra(report: dict, spec: PhantomSpec, device: dict[str, str] | None) -> dict:
    """What the calibration file keeps of the run's report."""
    return {**({"device": dict(device)} if device else {}), "rms_px": report["rms_px"],
            "images": [{"image": e["image"], "balls": e["balls_used"], "rms_px": e["rms_px"],
                        "tilt_deg": e["tilt_deg"], "outlier_balls": len(e["outlier_balls"])}
                       for e in report["images"] if e["used"]],
            "rejected": [{"image": e["image"], "reason": e["reason"]} for e in report["images"] if not e["used"]],
            "phantom": spec.to_json(), "principal_point": report["principal_point"],
            "intrinsics_sd": {n: v["sd"] for n, v in report["intrinsics"].items()},
            "plate": {k: v for k, v in report["plate"].items() if k != "balls_mm"}}


def _rms(m: bundle.Bundle, x: np.ndarray, obs: bundle.Observations, k: int,
         outliers: bool = False) -> float:
    """A frame's RMS over its balls (and, with ``outliers``, over its outliers too)."""
    r = bundle.ball_residuals(m, x, obs)[(obs.frame == k) & (obs.active | (outliers & (obs.ball >= 0)))]
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("inf")


def _sigmas(result, obs: bundle.Observations, held: bool = False) -> np.ndarray:
    """Standard deviations of the seven intrinsics (0 for a held principal point)."""
    s = bundle.parameter_sigmas(result, 2 * int(obs.active.sum()))
    if held:
        return np.concatenate([s[:1], [0.0, 0.0], s[1:6]])
    return s[:7]


def _fill_report(run: _Run, frames: list[_Frame], m: bundle.Bundle, x: np.ndarray,
                 obs: bundle.Observations, spec: PhantomSpec) -> None:
    r = bundle.ball_residuals(m, x, obs)
    for k, f in enumerate(frames):
        mine = obs.frame == k
        a = obs.active[mine]
        entry = run.entries[f.image.name]
        entry.update(used=True, reason=None, balls_used=int(a.sum()), tilt_deg=f.tilt_deg,
                     rms_px=float(np.sqrt(np.mean(r[mine][a] ** 2))),
                     outlier_balls=[_outlier(b, uv, e, spec) for b, uv, e in
                                    zip(obs.ball[mine][~a], obs.uv[mine][~a], r[mine][~a])])


def _outlier(ball: int, uv: np.ndarray, residual: float, spec: PhantomSpec) -> dict:
    """A blob the fit left out: where it is, and which ball it was taken for (if any)."""
    at = [round(float(u), 1) for u in uv]
    if ball < 0:
        return {"ball": None, "at_px": at, "residual_px": None,
                "why": "on no ball of the plate (a speck, or the grid continued beyond the plate)"}
    return {"ball": [int(ball % spec.cols), int(ball // spec.cols)], "at_px": at,
            "residual_px": round(float(residual), 2), "why": "far off the fit"}


def _plate_report(m: bundle.Bundle, x: np.ndarray, obs: bundle.Observations) -> dict:
    if m.basis is None:
        return {"refined": False}
    offsets = m.plate(x) - m.nominal
    seen = np.unique(obs.ball[obs.active])
    norms = np.linalg.norm(offsets[seen], axis=1)
    return {"refined": True, "balls_seen": int(len(seen)),
            "error_rms_mm": float(np.sqrt(np.mean(norms**2))), "error_max_mm": float(norms.max()),
            "note": "ball offsets from the perfect grid, up to a shift, rotation and scale of "
                    "the whole plate (the pitch is only a scale)",
            "balls_mm": [[round(float(v), 4) for v in o] for o in offsets]}
