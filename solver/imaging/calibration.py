"""C-arm calibration from ball-grid phantom images, and the versioned calibration file.

Estimation (:func:`calibrate`):

1. Balls are found in each image's attenuation (any polarity, inside the circular field,
   vignetting removed by a local median background) as compact blobs of the expected size;
   blobs cut by the rim of the field or merged with other metal are refused. Their centres
   are attenuation-weighted centroids.
2. The grid: neighbouring balls give the two lattice directions; integer grid coordinates
   are propagated from the central ball, each step predicted from the last observed step,
   so perspective and distortion do not break it and missing balls are simply absent. The
   grid is symmetric and the plate transparent, so any consistent labelling is a valid pose.
3. A first guess (OpenCV, one focal length, principal point fixed at the field's centre, no
   distortion) gives each plate pose; then all parameters are refined jointly (bundle
   adjustment with scipy): one focal length (square pixels, or the known pixel aspect), the
   principal point bounded to ``max_principal_offset_px`` of the field's centre, the
   image-intensifier distortion (``solver.imaging.distortion``, centred on the field) and
   every plate pose.

Guards: unconstrained C-arm calibrations are known to return unequal focal lengths and
principal points off the image; here the focal lengths are tied, the principal point is
bounded, a principal point that the set cannot determine (its standard error above
``max_principal_sigma_px``) is held at the field's centre, and a focal length far from the
nominal ``SID / pixel spacing`` is refused. Sets with too few usable images, with all plates
nearly fronto-parallel, or with inconsistent image sizes or pixel spacings are refused.

File (DESIGN.md section 6), ``slamtka-calibration/2``: id, description, creation time,
detector (size and pixel spacing), camera (K and field radius), distortion, RMS overall and
per image, rejected images with their reason, the phantom, and a sha256 over the rest.
Version 1 files (no distortion, no pixel spacing) still load.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from ..camera import Camera
from ..jsonfile import read_json_object
from .distortion import Distortion
from .field import FieldError, attenuation, field_of_view
from .phantom import PhantomSpec

__all__ = ["Calibration", "CalibrationError", "CalibrationOptions", "CalibrationImage",
           "calibrate", "detect_balls", "match_grid", "load_calibration", "calibration_document",
           "write_calibration",
           "FORMAT", "FORMAT_V1"]

FORMAT = "slamtka-calibration/2"
FORMAT_V1 = "slamtka-calibration/1"


class CalibrationError(ValueError):
    """A calibration set, file or frame that cannot be used, with the reason."""


# -- the calibration as the pipeline uses it ------------------------------------------------

@dataclass
class Calibration:
    """One C-arm's intrinsics, distortion and detector, as loaded from its file."""

    camera: Camera
    distortion: Distortion | None  # None: images carry no distortion (or are corrected)
    calibration_id: str
    sha256: str
    pixel_spacing_mm: tuple[float, float] | None
    _document: dict = field(repr=False, default_factory=dict)

    def document(self) -> dict:
        """The calibration file's content (for audit records)."""
        return self._document

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixel positions (N, 2) of raw observed positions (N, 2)."""
        uv = self._points(uv)
        return uv if self.distortion is None or len(uv) == 0 else self.distortion.undistort(uv)

    def distort_points(self, uv: np.ndarray) -> np.ndarray:
        """Raw (as imaged) pixel positions (N, 2) of ideal pinhole positions (N, 2)."""
        uv = self._points(uv)
        return uv if self.distortion is None or len(uv) == 0 else self.distortion.distort(uv)

    @staticmethod
    def _points(uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, float)
        if uv.size == 0:
            return np.zeros((0, 2))
        if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
            raise CalibrationError(f"pixel positions must be finite (N, 2), got shape {uv.shape}")
        return uv.copy()

    def check_frame(self, frame_or_width, height: int | None = None,
                    pixel_spacing: tuple[float, float] | None = None) -> str | None:
        """Why a frame must be refused with this calibration, or None when it matches.

        Takes a frame (anything with ``width``, ``height`` and ``imager_pixel_spacing_mm``,
        such as ``service.frames.Frame``) or its width, height and pixel spacing (mm).
        """
        if height is None:
            frame = frame_or_width
            width, height = frame.width, frame.height
            pixel_spacing = frame.imager_pixel_spacing_mm
        else:
            width = frame_or_width
        if (width, height) != (self.camera.width, self.camera.height):
            return (f"frame is {width}x{height} px but calibration {self.calibration_id} is for "
                    f"{self.camera.width}x{self.camera.height} px")
        if self.pixel_spacing_mm is not None and pixel_spacing is not None and not np.allclose(
                pixel_spacing, self.pixel_spacing_mm, rtol=1e-3, atol=1e-5):
            return (f"frame pixel spacing {list(pixel_spacing)} mm differs from calibration "
                    f"{self.calibration_id} ({list(self.pixel_spacing_mm)} mm)")
        return None


def _digest(body: dict) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def calibration_document(camera: Camera, calibration_id: str, description: str,
                         distortion: Distortion | None = None,
                         pixel_spacing_mm: tuple[float, float] | None = None,
                         extra: dict | None = None) -> dict:
    """The versioned, checksummed calibration file content."""
    body = {"format": FORMAT, "id": calibration_id, "description": description,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "detector": {"width": camera.width, "height": camera.height,
                         "pixel_spacing_mm": None if pixel_spacing_mm is None else list(pixel_spacing_mm)},
            "camera": camera.to_json(),
            "distortion": {"model": "none"} if distortion is None else distortion.to_json(),
            **(extra or {})}
    return {**body, "sha256": _digest(body)}


def write_calibration(path: str | Path, camera: Camera, distortion: Distortion | None,
                      description: str, calibration_id: str | None = None,
                      pixel_spacing_mm: tuple[float, float] | None = None,
                      extra: dict | None = None) -> Calibration:
    """Write a calibration file (whole, then renamed into place) and return it as loaded."""
    path = Path(path)
    doc = calibration_document(camera, calibration_id or path.stem, description, distortion,
                               pixel_spacing_mm, extra)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(doc, indent=2))
    temporary.replace(path)
    return load_calibration(path)


def load_calibration(path: str | Path) -> Calibration:
    """Read and verify a calibration file (version 2, or version 1 without distortion)."""
    path = Path(path)
    try:
        doc = read_json_object(path)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    if doc.get("format") not in (FORMAT, FORMAT_V1):
        raise CalibrationError(f"{path}: format {doc.get('format')!r} "
                               f"is not {FORMAT!r} or {FORMAT_V1!r}")
    body = {k: v for k, v in doc.items() if k != "sha256"}
    if doc.get("sha256") != _digest(body):
        raise CalibrationError(f"{path}: calibration checksum does not match its content")
    try:
        camera = Camera.from_json(doc["camera"])
        distortion_doc = doc.get("distortion") or {"model": "none"}
        if not isinstance(distortion_doc, dict):
            raise TypeError(f"distortion must be an object with a model, "
                            f"not {type(distortion_doc).__name__}")
        distortion = None if distortion_doc.get("model") == "none" else Distortion.from_json(distortion_doc)
        spacing = (doc.get("detector") or {}).get("pixel_spacing_mm")
        spacing = None if spacing is None else (float(spacing[0]), float(spacing[1]))
        calibration_id = str(doc["id"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CalibrationError(f"{path}: malformed calibration ({exc})") from None
    return Calibration(camera, distortion, calibration_id, doc["sha256"], spacing, doc)


# -- ball detection and the grid ------------------------------------------------------------

def detect_balls(image: np.ndarray, ball_diameter_px: tuple[float, float] = (8.0, 60.0),
                 polarity: str = "auto", min_contrast: float = 0.25) -> np.ndarray:
    """Centres (N, 2) of ball shadows: compact blobs of a plausible size, not cut by the rim."""
    centre, radius, outside, sign = field_of_view(np.asarray(image), polarity, "phantom")
    A = attenuation(image, outside, sign)
    h, w = A.shape
    v, u = np.mgrid[0:h, 0:w]
    r = np.hypot(u - centre[0], v - centre[1])
    lit = r < (radius if radius is not None else np.inf) - 1.0
    A = np.where(lit, A, np.median(A[lit])).astype(np.float32)
    # Background at a scale several balls wide (median ignores the balls themselves).
    small = cv2.resize(A, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(small, [1, 99])
    q = np.clip((small - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    k = int(ball_diameter_px[1] / 4) | 1
    background = cv2.medianBlur(q, max(5, 2 * k + 1)).astype(np.float32) / 255 * (hi - lo) + lo
    excess = A - cv2.resize(background, (w, h), interpolation=cv2.INTER_LINEAR)
    blobs = (excess > min_contrast) & lit
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(blobs.astype(np.uint8), connectivity=8)
    d_lo, d_hi = ball_diameter_px
    area = stats[:, cv2.CC_STAT_AREA].astype(float)
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    fill = area / np.maximum(bw * bh, 1)
    round_ = (np.abs(bw - bh) <= 0.35 * np.maximum(bw, bh)) & (fill > 0.6)
    sized = (area >= np.pi / 4 * d_lo**2) & (area <= np.pi / 4 * d_hi**2)
    # A blob touching the rim of the field is partly hidden: its centroid is biased.
    far = np.sqrt(area / np.pi) + 3.0
    inside = np.linalg.norm(centroids - centre, axis=1) + far < (radius if radius is not None else np.inf)
    keep = round_ & sized & inside
    keep[0] = False
    index = np.nonzero(keep)[0]
    if len(index) == 0:
        return np.zeros((0, 2))
    weights = np.where(blobs, excess, 0.0)
    mass = ndimage.sum(weights, labels, index)
    cu = ndimage.sum(weights * u, labels, index) / mass
    cv = ndimage.sum(weights * v, labels, index) / mass
    return np.column_stack([cu, cv])


def match_grid(points: np.ndarray, rows: int, cols: int, min_balls: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid coordinates of detected balls: (indices into ``points``, (K, 2) integer (col, row)).

    Raises :class:`CalibrationError` when no consistent grid of at least ``min_balls`` is found.
    """
    if len(points) < min_balls:
        raise CalibrationError(f"only {len(points)} balls found, need {min_balls}")
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    start = int(np.argmin(np.linalg.norm(points - np.median(points, axis=0), axis=1)))
    near = np.argsort(d[start])[:4]
    steps = points[near] - points[start]
    a = steps[0]
    b = steps[int(np.argmin(np.abs(steps @ a) / (np.linalg.norm(steps, axis=1) * np.linalg.norm(a))))]
    coords = {start: (0, 0)}
    basis = {start: (a, b)}
    queue = [start]
    taken = {(0, 0): start}
    while queue:
        i = queue.pop(0)
        ci, (ai, bi) = coords[i], basis[i]
        for step, delta in ((ai, (1, 0)), (-ai, (-1, 0)), (bi, (0, 1)), (-bi, (0, -1))):
            target = (ci[0] + delta[0], ci[1] + delta[1])
            guess = points[i] + step
            j = int(np.argmin(np.linalg.norm(points - guess, axis=1)))
            if np.linalg.norm(points[j] - guess) > 0.3 * spacing:
                continue
            if j in coords:
                if coords[j] != target:
                    raise CalibrationError("ball positions do not form a consistent grid")
                continue
            if target in taken:
                raise CalibrationError("two balls claim the same grid position")
            observed = points[j] - points[i]
            new_a = observed * delta[0] if delta[0] else ai
            new_b = observed * delta[1] if delta[1] else bi
            coords[j], basis[j], taken[target] = target, (new_a, new_b), j
            queue.append(j)
    index = np.array(list(coords))
    grid = np.array([coords[i] for i in index])
    grid -= grid.min(axis=0)
    span = grid.max(axis=0) + 1
    if not ((span[0] <= cols and span[1] <= rows) or (span[0] <= rows and span[1] <= cols)):
        raise CalibrationError(f"the balls span {span[0]}x{span[1]} positions, more than the "
                               f"{cols}x{rows} grid: another object looks like a ball")
    if len(index) < min_balls:
        raise CalibrationError(f"only {len(index)} balls form a grid, need {min_balls}")
    return index, grid


# -- estimation -----------------------------------------------------------------------------

@dataclass(frozen=True)
class CalibrationOptions:
    min_images: int = 6
    min_balls: int = 12
    min_max_tilt_deg: float = 10.0  # some plate must be tilted at least this much
    max_principal_offset_px: float = 60.0  # principal point bound around the field centre
    max_principal_sigma_px: float = 8.0  # beyond: the set cannot fix it, hold it at the centre
    max_focal_deviation: float = 0.15  # from SID / pixel spacing, when both are known
    max_rms_px: float = 1.0


@dataclass
class CalibrationImage:
    """One phantom frame as handed to :func:`calibrate`."""

    name: str
    pixels: np.ndarray
    pixel_spacing_mm: tuple[float, float] | None = None
    sid_mm: float | None = None


def _project(params: np.ndarray, views: list[np.ndarray], aspect: float,
             base: Distortion) -> list[np.ndarray]:
    """Pixels of each view's plate points (``views``, plate frame) under the calibration
    ``params``: focal length, principal point, distortion, then each view's plate pose."""
    f, cx, cy = params[:3]
    distortion = base.with_params(params[3:7])
    out = []
    for k, pts in enumerate(views):
        rvec, tvec = params[7 + 6 * k: 10 + 6 * k], params[10 + 6 * k: 13 + 6 * k]
        R = cv2.Rodrigues(rvec)[0]
        p = pts @ R.T + tvec
        uv = np.column_stack([f * p[:, 0] / p[:, 2] + cx, f * aspect * p[:, 1] / p[:, 2] + cy])
        out.append(distortion.distort(uv))
    return out


def calibrate(images: list[CalibrationImage], spec: PhantomSpec = PhantomSpec(),
              options: CalibrationOptions = CalibrationOptions(), calibration_id: str = "carm",
              description: str = "") -> tuple[Calibration, dict]:
    """Estimate a :class:`Calibration` from phantom frames; also returns a report.

    Frames where the grid is not found are reported by name in the report (and the file),
    not fatal; a set that cannot determine the camera raises :class:`CalibrationError`.
    """
    if not images:
        raise CalibrationError("no calibration images given")
    shapes = {im.pixels.shape for im in images}
    if len(shapes) != 1:
        raise CalibrationError(f"images have different sizes {sorted(shapes)}; one C-arm, one size")
    spacings = {im.pixel_spacing_mm for im in images if im.pixel_spacing_mm is not None}
    if len(spacings) > 1:
        raise CalibrationError(f"images have different pixel spacings {sorted(spacings)}")
    spacing = next(iter(spacings)) if spacings else None
    height, width = next(iter(shapes))
    aspect = 1.0 if spacing is None else spacing[1] / spacing[0]  # fy / fx = col / row spacing

    used, rejected, fields = [], [], []
    for im in images:
        try:
            centre, radius, _, _ = field_of_view(im.pixels, "auto", "phantom")
            balls = detect_balls(im.pixels)
            index, grid = match_grid(balls, spec.rows, spec.cols, options.min_balls)
        except (CalibrationError, FieldError) as exc:
            rejected.append({"image": im.name, "reason": str(exc)})
            continue
        # Grid (col, row) -> plate point; any consistent labelling is a valid plate pose.
        plate_points = np.column_stack([(grid[:, 0] - (spec.cols - 1) / 2) * spec.pitch_mm,
                                        (grid[:, 1] - (spec.rows - 1) / 2) * spec.pitch_mm,
                                        np.zeros(len(grid))])
        used.append((im, plate_points, balls[index]))
        fields.append((centre, radius))
    if len(used) < options.min_images:
        names = "; ".join(f"{r['image']}: {r['reason']}" for r in rejected) or "none rejected"
        raise CalibrationError(f"only {len(used)} usable images, need {options.min_images} "
                               f"(rejected: {names})")
    centre = np.median([c for c, _ in fields], axis=0)
    radii = [r for _, r in fields if r is not None]
    radius = float(np.median(radii)) if radii else None
    base = Distortion(float(centre[0]), float(centre[1]), radius or max(width, height) / 2.0)

    nominal = None
    sids = [im.sid_mm for im, _, _ in used if im.sid_mm]
    if spacing is not None and sids:
        nominal = float(np.median(sids)) / spacing[1]
    # First guess: OpenCV with one focal length, principal point at the field centre.
    f0 = nominal or 4.0 * max(width, height)
    K0 = np.array([[f0, 0, centre[0]], [0, f0 * aspect, centre[1]], [0, 0, 1]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    _, K1, _, rvecs, tvecs = cv2.calibrateCamera(
        [p.astype(np.float32) for _, p, _ in used], [o.astype(np.float32) for _, _, o in used],
        (width, height), K0, np.zeros(5), flags=flags)
    tilts = [np.degrees(np.arccos(abs(cv2.Rodrigues(r)[0][2, 2]))) for r in rvecs]
    if max(tilts) < options.min_max_tilt_deg:
        raise CalibrationError(f"all plates are nearly fronto-parallel (largest tilt {max(tilts):.1f} deg, "
                               f"need {options.min_max_tilt_deg}); tilt the phantom")

    off = options.max_principal_offset_px
    poses = [np.concatenate([r.ravel(), t.ravel()]) for r, t in zip(rvecs, tvecs)]
    for _ in range(2):
        # A frame whose balls were mislabelled fits far worse than the others: drop it, refit.
        observed = np.concatenate([o for _, _, o in used])
        views = [p for _, p, _ in used]

        def residuals(x: np.ndarray) -> np.ndarray:
            return (np.concatenate(_project(x, views, aspect, base)) - observed).ravel()

        x0 = np.concatenate([[K1[0, 0], centre[0], centre[1], 0.0, 0.0, 0.0, 0.0], *poses])
        lower = np.full(len(x0), -np.inf)
        upper = np.full(len(x0), np.inf)
        lower[:7] = [0.2 * x0[0], centre[0] - off, centre[1] - off, -0.5, -0.5, -0.2, -0.2]
        upper[:7] = [5.0 * x0[0], centre[0] + off, centre[1] + off, 0.5, 0.5, 0.2, 0.2]
        solution = least_squares(residuals, x0, bounds=(lower, upper), x_scale="jac", method="trf")
        errors = [np.sqrt(np.mean(np.sum((p - o) ** 2, axis=1))) for p, (_, _, o) in
                  zip(_project(solution.x, views, aspect, base), used)]
        worst = max(0.5, 5.0 * float(np.median(errors)))
        bad = [k for k, e in enumerate(errors) if e > worst]
        if not bad or len(used) - len(bad) < options.min_images:
            break
        rejected += [{"image": used[k][0].name, "reason": f"does not fit the other images "
                      f"(RMS {errors[k]:.2f} px): grid mislabelled or plate moved"} for k in bad]
        used = [u for k, u in enumerate(used) if k not in bad]
        poses = [q for k, q in enumerate(poses) if k not in bad]
        tilts = [t for k, t in enumerate(tilts) if k not in bad]
    x = solution.x
    J = solution.jac
    dof = max(1, len(solution.fun) - len(x))
    sigma2 = float(solution.fun @ solution.fun) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
        pp_sigma = float(np.sqrt(max(cov[1, 1], cov[2, 2])))
    except np.linalg.LinAlgError:
        pp_sigma = np.inf
    principal_held = bool(pp_sigma > options.max_principal_sigma_px)
    if principal_held:
        keep = np.ones(len(x), bool)
        keep[1:3] = False

        def reduced(y: np.ndarray) -> np.ndarray:
            full = x.copy()
            full[keep] = y
            full[1:3] = centre
            return residuals(full)

        y = least_squares(reduced, x[keep], bounds=(lower[keep], upper[keep]), x_scale="jac").x
        x[keep], x[1:3] = y, centre
    f, cx, cy = float(x[0]), float(x[1]), float(x[2])
    if nominal is not None and abs(f / nominal - 1.0) > options.max_focal_deviation:
        raise CalibrationError(f"estimated focal length {f:.0f} px is {100 * (f / nominal - 1):+.0f}% from "
                               f"the nominal SID / pixel spacing {nominal:.0f} px: implausible")
    projected = _project(x, views, aspect, base)
    per_image = [{"image": im.name, "balls": len(o),
                  "rms_px": float(np.sqrt(np.mean(np.sum((p - o) ** 2, axis=1)))), "tilt_deg": float(t)}
                 for (im, _, o), p, t in zip(used, projected, tilts)]
    rms = float(np.sqrt(np.mean(np.sum((np.concatenate(projected) - observed) ** 2, axis=1))))
    if rms > options.max_rms_px:
        raise CalibrationError(f"calibration RMS {rms:.2f} px exceeds {options.max_rms_px} px: "
                               "the images do not fit one camera (different C-arms or settings?)")
    camera = Camera(f, f * aspect, cx, cy, width, height, radius)
    distortion = base.with_params(x[3:7])
    extra = {"rms_px": rms, "images": per_image, "rejected": rejected, "phantom": spec.to_json(),
             "principal_point": {"held_at_field_centre": principal_held, "sigma_px": pp_sigma}}
    doc = calibration_document(camera, calibration_id, description or "C-arm calibration from phantom",
                               distortion, spacing, extra)
    report = {"rms_px": rms, "images": per_image, "rejected": rejected, "used": len(used),
              "principal_held": principal_held, "principal_sigma_px": pp_sigma}
    return Calibration(camera, distortion, calibration_id, doc["sha256"], spacing, doc), report
