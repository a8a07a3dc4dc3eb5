"""The lit field of an X-ray frame and its attenuation image, shared by contours and calibration.

Two detectors are met in the operating room. An image intensifier images a circle and its
frame's corners carry only a flat no-signal level; a flat panel images the whole (square)
frame, and its corners show air, the leg or a collimator shutter, with quantum noise. The
circle is accepted only when a flat level around the corners ends on a circle of plausible
size; otherwise the whole frame is the field.

Polarity (MONOCHROME2 with bone and metal dark, or an inverted image) comes from the content:
a knee frame is centred on the leg, so its periphery is less attenuating than its centre
(:func:`_periphery_asymmetry`); where that is not clear, steel pins, the narrow bodies that
attenuate most, stand out on the attenuating side (:func:`polarity_sign`). Only when both are
ambiguous does the intensifier's no-signal level decide (the side it lies on is "no signal").
:class:`FieldOfView` says whether the polarity came from clear evidence, so that a case's
frames can be read alike (``contours.agreed_polarity``).

``-log(signal)`` turns the frame into attenuation, in which bodies add. Collimator blades
that scatter and processing leave short of opaque are found from their straight edges
across the field (:func:`collimator_shutters`).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

__all__ = ["FieldError", "FieldOfView", "field_of_view", "attenuation", "collimator_shutters", "components",
           "fill_holes", "polarity_sign", "remove_overlays"]


class FieldError(ValueError):
    """A frame whose field of view cannot be found, with the reason."""


def _fit_circle(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
    """Circle through most of the points (RANSAC over triplets), refined by least squares,
    and the share of the points on it, of those not inside it.

    Objects crossing the rim of the field (a pin sticking out, retractor blades as dark as
    no signal) dent its boundary inwards, so the consensus circle, not a plain fit, is the
    field, and what they add inside it does not count against it.
    """
    triplets = points[rng.integers(0, len(points), (300, 3))]
    a, b, c = triplets[:, 0], triplets[:, 1], triplets[:, 2]
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    ok = np.abs(d) > 1e-6
    if not ok.any():
        return np.zeros(2), np.inf, 0.0
    a, b, c, d = a[ok], b[ok], c[ok], d[ok]
    sa, sb, sc = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    centres = np.column_stack([
        (sa * (b[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - b[:, 1])) / d,
        (sa * (c[:, 0] - b[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (b[:, 0] - a[:, 0])) / d])
    radii = np.linalg.norm(a - centres, axis=1)
    # Score candidates on a subsample of the boundary to keep this vectorised and small.
    sample = points[:: max(1, len(points) // 400)]
    du, dv = sample[None, :, 0] - centres[:, 0, None], sample[None, :, 1] - centres[:, 1, None]
    residual = np.abs(np.sqrt(du * du + dv * dv) - radii[:, None])
    best = int(np.argmax((residual < 1.5).sum(axis=1)))
    off = np.linalg.norm(points - centres[best], axis=1) - radii[best]
    keep = np.abs(off) < 1.5
    share = float(keep.sum() / max(np.count_nonzero(off > -1.5), 1))
    p = points[keep]
    if len(p) < 3:
        return centres[best], float(radii[best]), share
    M = np.column_stack([2 * p, np.ones(len(p))])
    sol = np.linalg.lstsq(M, (p**2).sum(axis=1), rcond=None)[0]
    r2 = sol[2] + sol[:2] @ sol[:2]
    return sol[:2], float(np.sqrt(max(r2, 0.0))), share


# A circle is the intensifier's field only if this share of the flat region's boundary not
# inside it lies on it, its radius is this share of the frame's shorter side to its diagonal, and its
# boundary points span this arc about its centre (a straight skin line fits a huge circle).
_CIRCLE_INLIERS = 0.35
_CIRCLE_RADIUS = (0.25, 0.8)
_CIRCLE_ARC_DEG = 180.0


def _circular_field(image: np.ndarray, span: float) -> tuple[np.ndarray, float, float] | None:
    """The intensifier's circle (centre, radius) and no-signal level, or None."""
    h, w = image.shape
    c = max(4, min(h, w) // 64)
    patches = [image[:c, :c], image[:c, -c:], image[-c:, :c], image[-c:, -c:]]
    levels = np.array([np.median(p) for p in patches])
    noise = max(float(np.max([np.std(p) for p in patches])), 1e-3 * span)
    # No-signal corners are flat and at one level; corners with air or the leg are not.
    if noise > 0.02 * span or np.ptp(levels) > 0.02 * span:
        return None
    outside = float(np.median(levels))
    flat = np.abs(image - outside) <= max(4.0 * noise, 0.01 * span)
    count, labels = cv2.connectedComponents(flat.astype(np.uint8), connectivity=8)
    corner_labels = np.unique([labels[0, 0], labels[0, -1], labels[-1, 0], labels[-1, -1]])
    corner_labels = corner_labels[corner_labels > 0]
    if len(corner_labels) == 0:
        return None
    at_corner = np.zeros(count, bool)
    at_corner[corner_labels] = True
    region = fill_holes(~at_corner[labels]).astype(np.uint8)
    boundary = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    if not boundary:
        return None
    points = np.vstack([b.reshape(-1, 2) for b in boundary]).astype(float)
    # Drop the frame's border: the field may be cut by the frame.
    points = points[(points[:, 0] > 1) & (points[:, 1] > 1) & (points[:, 0] < w - 2) & (points[:, 1] < h - 2)]
    if len(points) < 50:
        return None
    centre, radius, share = _fit_circle(points, np.random.default_rng(0))
    if not (np.isfinite(radius) and share >= _CIRCLE_INLIERS
            and _CIRCLE_RADIUS[0] * min(h, w) <= radius <= _CIRCLE_RADIUS[1] * np.hypot(h, w)
            and -0.25 * w <= centre[0] <= 1.25 * w and -0.25 * h <= centre[1] <= 1.25 * h):
        return None
    on = points[np.abs(np.linalg.norm(points - centre, axis=1) - radius) < 1.5]
    angles = np.sort(np.arctan2(on[:, 1] - centre[1], on[:, 0] - centre[0]))
    gaps = np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi]))
    if np.degrees(2 * np.pi - gaps.max()) < _CIRCLE_ARC_DEG:
        return None
    return centre, radius, outside


_BAR_CONTRASTS = (0.1, 0.2, 0.3, 0.5)  # of the central field's 1-99 percentile range
_CENTRAL_SHARE = 0.7  # of the field's half-size: where steel bars are looked for


def polarity_sign(image: np.ndarray, lit: np.ndarray) -> int | None:
    """+1 if attenuating bodies are dark, -1 if bright, None if the content does not say.

    At a quarter of the resolution (thin burned-in text strokes fade there; a pin 3 mm
    thick stays several pixels wide) the black and white top-hats with an element wider
    than a pin pick the narrow bodies darker and brighter than their surroundings. Steel
    bars stand out most, on the attenuating side. Outside the field (and beyond the frame)
    each top-hat sees the extreme of its own sign, so that no strip of air along the rim
    or the frame's edge passes for a bar."""
    small = cv2.resize(image.astype(np.float32), None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    inside = cv2.resize(lit.astype(np.uint8), small.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    # The pins are near the centre of a knee frame; the periphery holds what misleads: air
    # strips beside the skin, collimator blades, annotations.
    vs, us = np.nonzero(inside)
    if len(us) == 0:
        return None
    centre = np.array([us.mean(), vs.mean()])
    reach = _CENTRAL_SHARE * 0.5 * min(np.ptp(us) + 1, np.ptp(vs) + 1)
    gv, gu = np.mgrid[0:small.shape[0], 0:small.shape[1]]
    central = inside & (np.hypot(gu - centre[0], gv - centre[1]) < reach)
    if central.sum() < 400:
        return None
    lo, hi = np.percentile(small[central], [1, 99])
    if hi - lo <= 0:
        return None
    norm = np.clip((small - lo) / (hi - lo), -0.5, 1.5)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (17, 17))
    pad = 9
    shares = []
    for op, fill in ((cv2.MORPH_BLACKHAT, -0.5), (cv2.MORPH_TOPHAT, 1.5)):
        padded = cv2.copyMakeBorder(np.where(inside, norm, fill).astype(np.float32), pad, pad, pad, pad,
                                    cv2.BORDER_CONSTANT, value=fill)
        hat = cv2.morphologyEx(padded, op, kernel)[pad:-pad, pad:-pad]
        # Over several contrasts: steel stands out at all of them, in linear and log frames.
        shares.append(float(sum(np.mean(hat[central] > t) for t in _BAR_CONTRASTS)))
    dark_share, bright_share = shares
    if max(shares) < 5e-4 or max(shares) < 1.5 * min(shares):
        return None
    return 1 if dark_share > bright_share else -1


# The periphery's asymmetry (below), in parts of the field's 1-99 percentile range, that
# decides the polarity on its own, and that decides it when the steel does not.
_RIM_DECISIVE = 0.15
_RIM_WEAK = 0.03


def _periphery_asymmetry(image: np.ndarray, lit: np.ndarray, centre: np.ndarray,
                         radius: float | None) -> float:
    """Positive when the field's periphery is brighter than its centre, negative if darker.

    A knee frame is centred on the leg, thickest (and holding the bone) in the middle:
    the periphery shows air or thinner tissue, less attenuating than the centre, on at
    least some sides, and collimator blades, more attenuating, on at most a few. So the
    periphery's less attenuating quarter departs further from the centre's level than
    its most attenuating quarter: its upper quartile in a frame with bone dark, its lower
    one in an inverted frame."""
    h, w = image.shape
    u, v = np.arange(0, w, 2)[None, :], np.arange(0, h, 2)[:, None]
    if radius is not None:
        rel = np.hypot(u - centre[0], v - centre[1]) / radius
    else:
        rel = np.maximum(np.abs(u - centre[0]) / (w / 2.0), np.abs(v - centre[1]) / (h / 2.0))
    sub, inside = image[::2, ::2], lit[::2, ::2]
    core, ring = sub[inside & (rel < 0.3)], sub[inside & (rel > 0.8)]
    if len(core) < 50 or len(ring) < 50:
        return 0.0
    lo, hi = np.percentile(sub[inside], [1, 99])
    if hi <= lo:
        return 0.0
    level = float(np.median(core))
    q25, q75 = np.percentile(ring, [25, 75])
    return float(((q75 - level) - (level - q25)) / (hi - lo))


class FieldOfView(NamedTuple):
    """Where a frame is lit, and which way its grey levels run."""

    centre: np.ndarray
    radius: float | None  # None: the whole frame is imaged
    level: float  # the grey level of no signal
    sign: int  # +1: attenuating bodies dark, -1: bright
    # Whether the sign was configured or read from clear evidence (a knee frame's periphery
    # beyond _RIM_DECISIVE, a phantom's no-signal level), not from the weaker cues that a
    # collimator blade's edge can mislead (shutters seeds 14 and 23, view 1).
    sign_decisive: bool


def field_of_view(image: np.ndarray, polarity: str, scene: str = "knee") -> FieldOfView:
    """Centre, radius, no-signal level and sign of signal of a frame.

    ``scene`` "knee" reads an automatic polarity from the content of a knee frame first;
    "phantom" (a calibration plate filling the field, no leg) from the intensifier's
    no-signal level first."""
    data = np.asarray(image)
    if data.ndim != 2 or min(data.shape) < 16:
        raise FieldError(f"expected a 2-D grey-scale frame, got shape {data.shape}")
    data = data.astype(np.float32)
    if not np.all(np.isfinite(data)):
        raise FieldError("the frame has non-finite pixel values")
    h, w = data.shape
    lo, hi = (float(x) for x in np.percentile(data[::2, ::2], [0.1, 99.9]))
    span = hi - lo
    if span <= 0:
        raise FieldError("the frame is uniform (no contrast): nothing was imaged")
    circle = _circular_field(data, span)
    if circle is not None:
        centre, radius, outside = circle
        u, v = np.arange(w)[None, :], np.arange(h)[:, None]
        lit = np.hypot(u - centre[0], v - centre[1]) < radius - 4.0
    else:
        centre, radius, outside = np.array([(w - 1) / 2.0, (h - 1) / 2.0]), None, None
        lit = np.ones_like(data, bool)
    if polarity in ("dark", "bright"):
        sign, decisive = (1 if polarity == "dark" else -1), True
    else:
        guess: int | None = None
        if scene == "phantom" and outside is not None:
            guess = 1 if float(np.median(data[lit])) >= outside else -1
        rim = _periphery_asymmetry(data, lit, centre, radius) if guess is None else 0.0
        decisive = guess is not None or abs(rim) >= _RIM_DECISIVE
        if guess is None:
            guess = int(np.sign(rim)) if abs(rim) >= _RIM_DECISIVE else polarity_sign(data, lit)
        if guess is None and abs(rim) >= _RIM_WEAK:
            guess = int(np.sign(rim))
        if guess is None and outside is not None:
            guess = 1 if float(np.median(data[lit])) >= outside else -1
        if guess is None:
            raise FieldError("the polarity of the frame cannot be told (no steel stands out); "
                             "configure it")
        sign = guess
    inside = data[lit]
    level_lo, level_hi = float(inside.min()), float(inside.max())
    if outside is not None and sign * (np.median(inside) - outside) > 0:
        level = outside
    else:
        # No usable no-signal level: just beyond the most attenuating pixel of the field.
        level = level_lo - 1.0 if sign > 0 else level_hi + 1.0
    return FieldOfView(np.asarray(centre, float), radius, float(level), sign, decisive)


_STROKE_MIN_PX = 12
_STROKE_CONTRAST = 0.15  # of the frame's range: a stroke's mean step off its surroundings
# Of the frame's range: how near the extreme level a broad body's shadow is where the
# window clipped it. A clipped pin's core is at the extreme only in patches between noise
# (processing seed 18: 0-6% below it across a pin), text is at it throughout.
_NEAR_EXTREME = 0.1


def remove_overlays(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame with burned-in annotations filled in from around them, and their mask.

    Text and graphics are written at the extreme grey level of the stored range in strokes
    a few pixels wide; saturated air or the dark outside of a circular field are at that
    level too, but in broad areas that an opening keeps. Where a window clipped steel, the
    extreme level is broken by noise into patches: the body is the broad area near that
    level, which the opening keeps too, so no patch of it is a stroke (were it taken out,
    an inverted frame's pins would be lost with it). Strokes are filled in (Telea
    inpainting) so that they take no part in the field, the polarity or the edges."""
    data = np.asarray(image).astype(np.float32)
    mask = np.zeros(data.shape, bool)
    kernel = np.ones((7, 7), np.uint8)
    span = float(data.max() - data.min())
    for level in (data.max(), data.min()):
        at = data == level
        near = (np.abs(data - level) <= _NEAR_EXTREME * span).astype(np.uint8)
        broad = cv2.dilate(cv2.morphologyEx(near, cv2.MORPH_OPEN, kernel), np.ones((3, 3), np.uint8))
        thin = at & (broad == 0)
        # A stroke is a few dozen pixels at least (single pixels at the extreme are noise),
        # and stands sharply off what is around it; steel saturating the detector is at the
        # extreme too, but its surroundings (the rest of its shadow) are nearly as extreme.
        count, labels, areas = components(thin, 8)
        around = cv2.dilate(labels.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.int32)
        ring = (around > 0) & (labels == 0)
        contrast = np.bincount(around[ring], weights=np.abs(data[ring] - level), minlength=count).astype(float)
        contrast /= np.maximum(np.bincount(around[ring], minlength=count), 1) * max(span, 1e-9)
        stroke = (areas >= _STROKE_MIN_PX) & (contrast > _STROKE_CONTRAST)
        stroke[0] = False
        mask |= stroke[labels]
    if not mask.any():
        return data, mask
    mask = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return cv2.inpaint(data, mask.astype(np.uint8), 3, cv2.INPAINT_TELEA), mask


def attenuation(image: np.ndarray, outside: float, sign: int) -> np.ndarray:
    signal = sign * (image.astype(np.float32) - outside)
    return -np.log(np.maximum(signal, 1.0))


def components(mask: np.ndarray, connectivity: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Connected components of a mask: their count (with the background, label 0), labels
    and areas (px). The labels of ``cv2.connectedComponentsWithStats``, whose statistics
    take four times as long as the labelling."""
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=connectivity)
    return count, labels, np.bincount(labels.ravel(), minlength=count)


def fill_holes(mask: np.ndarray, max_area: int | None = None) -> np.ndarray:
    """The mask with its enclosed holes (smaller than ``max_area``, if given) filled."""
    count, labels, areas = components(~mask.astype(bool), 4)
    # A hole is enclosed when it does not reach the frame's border.
    fill = np.ones(count, bool)
    fill[labels[[0, -1], :]] = False
    fill[labels[:, [0, -1]]] = False
    if max_area is not None:
        fill &= areas < max_area
    return mask.astype(bool) | fill[labels]


# Collimator shutters (below): frames are searched at this fraction of their size, for
# straight edges within this many degrees of a side and this share of the frame from it.
_SHUTTER_SCALE = 4
_SHUTTER_ANGLES_DEG = np.arange(-10.0, 10.5, 1.0)
_SHUTTER_REACH = 0.35
_SHUTTER_BAND = 3  # rows (at the search scale) on either side of the edge that are compared
# A shutter's edge rises towards the frame's side by at least this attenuation over this
# share of its length in the field, and its line crosses this share of the field.
_SHUTTER_STEP = 0.15
_SHUTTER_ALONG = 0.75
_SHUTTER_SPAN = 0.5


def _side_views(x: np.ndarray) -> list[np.ndarray]:
    """``x`` seen with each side of the frame on top (top, bottom, left, right)."""
    return [x, x[::-1], x.T, x.T[::-1]]


def _from_side_view(view: np.ndarray, side: int) -> np.ndarray:
    """The inverse of :func:`_side_views` for one side."""
    return [view, view[::-1], view.T, view[::-1].T][side]


def collimator_shutters(A: np.ndarray, lit: np.ndarray) -> tuple[np.ndarray, list[tuple[int, float, float]]]:
    """Where collimator blades cover the frame (a mask), and their edges as ``(side,
    offset px, slope)`` with the frame's side on top: ``v = offset + slope (u - w / 2)``.

    A blade closes in from a side of the frame: its shadow is more attenuating than the
    field next to it, with a straight edge nearly parallel to that side that crosses the
    whole field, at every point of it a step up towards the side, and nothing beyond it is
    as clear as the field. A bone's shaft can be as straight and long, but has tissue or
    air beyond it; a flat panel with scatter and a C-arm's processing can leave a shutter
    too faint to count as opaque."""
    f = _SHUTTER_SCALE
    small = cv2.resize(A.astype(np.float32), None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
    seen = cv2.resize(lit.astype(np.uint8), small.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    seen = cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    b = _SHUTTER_BAND
    mask = np.zeros(A.shape, bool)
    lines: list[tuple[int, float, float]] = []
    slopes = np.tan(np.radians(_SHUTTER_ANGLES_DEG))
    for side, (x, m) in enumerate(zip(_side_views(small), _side_views(seen))):
        h, w = x.shape
        # Column sums of attenuation and of the seen field, for band means at any row.
        csum = np.vstack([np.zeros((1, w)), np.cumsum(np.where(m, x, 0.0), axis=0)])
        cnt = np.vstack([np.zeros((1, w)), np.cumsum(m, axis=0)])
        # Whether a band pair fits in the field and steps up outwards depends on its row and
        # column only: judged once per pixel, then read along every candidate line.
        at = np.arange(b, h - b + 1)
        out_n, in_n = cnt[at] - cnt[at - b], cnt[at + b] - cnt[at]
        inner = (csum[at + b] - csum[at]) / b
        step = (csum[at] - csum[at - b]) / b - inner
        # All the way out to the side, nothing is less attenuating than a blade's step over
        # the field (a bone's shaft, as straight and long, has tissue or air beyond it).
        least_out = np.minimum.accumulate(np.where(m, x, np.inf), axis=0)[at - 1]
        up = (step > _SHUTTER_STEP) & (least_out - inner > 0.5 * _SHUTTER_STEP)
        fits = (out_n == b) & (in_n == b)
        code = np.zeros((h, w), np.uint8)
        code[at] = fits.astype(np.uint8) + 2 * (fits & up).astype(np.uint8)
        rows = np.arange(b, int(_SHUTTER_REACH * h))
        u = np.arange(w)
        v = np.rint(rows[None, :, None] + slopes[:, None, None] * (u - w / 2.0)[None, None, :]).astype(int)
        ok = (v >= b) & (v <= h - b)
        line = np.where(ok, code.ravel()[np.clip(v, b, h - b) * w + u], 0)
        across = (line > 0).sum(axis=2)
        rising = (line > 1).sum(axis=2) / np.maximum(across, 1)
        # Across the field: the seen columns at that row, of those seen anywhere.
        span = across / max(int(m.any(axis=0).sum()), 1)
        good = (rising >= _SHUTTER_ALONG) & (span >= _SHUTTER_SPAN)
        if not good.any():
            continue
        # The innermost such edge: a shutter's penumbra steps over several rows.
        k, r = np.unravel_index(np.argmax(np.where(good, rows[None, :], -1)), good.shape)
        offset, slope = f * (rows[r] + 0.5) - 0.5, float(slopes[k])
        hh, ww = [A.shape, A.shape[::-1]][side // 2]
        vv, uu = np.arange(hh)[:, None], np.arange(ww)[None, :]
        # Out to the inner end of the compared band: the penumbra is no field.
        mask |= _from_side_view(vv < offset + f * b + slope * (uu - ww / 2.0), side)
        lines.append((side, float(offset), slope))
    return mask, lines
