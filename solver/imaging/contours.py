"""Automatic contour extraction: outer edges of tibia with fibula, and the edges of each pin.

Pipeline (all tuning in :class:`ContourConfig`):

1. Field of view and polarity. The circle of an image intensifier is found from the
   no-signal level in the frame's corners (a robust circle fit to the field's boundary);
   the polarity (attenuating objects dark or bright) is read from the frame's content
   (:func:`~slamtka.solver.imaging.field.field_of_view`). The frames of one case come from
   one C-arm: :func:`agreed_polarity` says when one read from weak cues must be read again
   as the clear ones read.
2. Attenuation. ``A = -log(signal)``, so that bodies add: soft tissue is a smooth surface,
   bone a step on top of it, metal a much larger one.
3. Pins: ``A`` minus a 100-px median background, and on and beside broad metal minus
   what it shows without anything as narrow as a pin (an opening by a disk wider than
   one): a pin crossing a retractor blade shows over it as over tissue. Seeded above
   ``pin_threshold`` and grown to half each shadow's peak; only bars of a pin's width and
   shape are kept (the plan's pin projected at the initial pose says which width), and a
   shadow holding straight bars of different directions (a pin across a blade seen
   edge-on) is cut into them.
   Seen nearly along the resection plane the two parallel pins often overlap, staggered
   along their common axis; steel saturates, so one shadow is split into two bars where
   its long sides step from one pin's edge to the other's (``pin_min_step_px``).
4. Bone: ``A`` minus a soft-tissue background (a low-order polynomial fitted by asymmetric
   least squares, so that it hugs the tissue under the bone) above ``bone_threshold``; the
   boundary of that mask, with its holes, is the coarse outer outline of tibia with fibula.
5. Sub-pixel edges: along each boundary point's outward normal, the position where ``A``
   falls fastest (smoothed derivative, parabolic peak) within ``edge_search_px`` (for the
   bone, ``bone_reach_in_px`` further inwards), kept when strong enough and away from the
   field's rim, the skin line and the pins' shadows. A bone edge is then placed at the mean
   of two estimates of the outline under the image's own blur: the steepest fall moved
   out, and the sharpest bend moved in.

Pin labels (rule): the two pins are ordered along their common axis direction, oriented
towards +u (image right): with ``pin_order = "left_to_right"`` pin 1 is the pin whose shadow
centre comes first. Mobile C-arm views of a knee look from behind within +-90 deg of AP with
the knee up, so the pin nearer the patient's -x (anatomical frame) comes first in every view;
a C-arm that mirrors its images uses ``"right_to_left"``. When an initial pose is known,
``expected_pins`` (the projected centres of pin 1 and pin 2) overrides the rule where it
tells the two pins apart clearly (its pose error is ~150 px at the pins).

Manual contours (the in-vivo protocol had the surgeon draw them) are read by
:func:`load_manual_contours`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from slamtka.solver.camera import Camera
from slamtka.solver.imaging.edges import (
    BoneEdgeSearch,
    bone_edges,
    edges_along_normals,
    gradient,
    kept_in,
    outline_with_normals,
    to_frame_pixels,
    to_working_pixels,
)
from slamtka.solver.imaging.field import (
    FieldError,
    collimator_shutters,
    components,
    field_of_view,
    fill_holes,
    remove_overlays,
)
from slamtka.solver.imaging.response import frame_attenuation
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.observations import ViewObservation, VisibleRegion

__all__ = ["VISIBLE_CELL_PX", "ContourConfig", "ExtractedContours", "agreed_polarity", "extract_contours",
           "load_manual_contours", "ContourError"]

VISIBLE_CELL_PX = 4  # the bone's visible region is kept in cells of this many pixels

_CONTOURS_FORMAT = "slamtka-contours/1"


class ContourError(FieldError):
    """A frame or contour document from which contours cannot be had, with the reason."""


@dataclass(frozen=True)
class ContourConfig:
    """Tuning of contour extraction (attenuation in natural-log units, lengths in px)."""

    polarity: str = "auto"  # "auto", "dark" (bone and metal dark) or "bright"
    fov_margin_px: float = 8.0  # edges this close to the field's rim are dropped
    smoothing_px: float = 1.2  # Gaussian sigma of the derivative used to place edges
    background_downscale: int = 8  # the soft-tissue surface is fitted this much smaller
    background_degree: int = 2  # polynomial degree of the soft-tissue surface
    air_margin: float = 0.35  # attenuation above the darkest field pixels still counted as air
    skin_margin_px: float = 40.0  # tissue this close to air seeds the soft-tissue region
    barrier_strength: float = 0.012  # attenuation change per px that soft tissue never has
    bone_threshold: float = 0.12  # attenuation over soft tissue above which a region is bone
    min_bone_area_px: int = 3000
    edge_search_px: float = 6.0  # half-length of the search for the edge along the normal
    min_edge_strength: float = 0.015  # attenuation drop per pixel at an accepted edge
    bone_edge_offset_px: float = 0.0  # outward shift of bone edges (blur bias of a site)
    bone_reach_in_px: float = 2.0  # further inward search: a gentle edge leaves the mask outside it
    # Attenuation over its pin-free background that seeds a steel shadow (grown to
    # half its peak); scatter brings steel down to ~0.6, bone's tangent cortex reaches ~0.9.
    pin_threshold: float = 0.5
    # Attenuation over the field's median above which a region wider than two pins is
    # opaque (collimator and retractor blades, a femur end-on); tibia with fibula stay below.
    opaque_excess: float = 1.5
    pin_width_px: tuple[float, float] = (12.0, 45.0)  # widths of pin shadows (3-4.5 mm, x1.6, 0.22 mm px)
    pin_min_area_px: int = 80
    pin_edge_offset_px: float = 0.0
    pin_min_step_px: float = 1.0  # least offset between overlapping pins' edges told apart
    pin_exclusion_px: float = 5.0  # bone edges this close to a pin shadow are dropped
    pin_order: str = "left_to_right"  # or "right_to_left" for mirrored images

    def __post_init__(self) -> None:
        if self.polarity not in ("auto", "dark", "bright"):
            raise ValueError(f"polarity must be auto, dark or bright, got {self.polarity!r}")
        if self.pin_order not in ("left_to_right", "right_to_left"):
            raise ValueError(f"pin_order must be left_to_right or right_to_left, got {self.pin_order!r}")
        if self.background_downscale < 1 or self.background_degree < 1:
            raise ValueError("background_downscale and background_degree must be >= 1")
        positive = ("smoothing_px", "edge_search_px", "barrier_strength", "bone_threshold",
                    "pin_threshold", "min_edge_strength", "pin_min_step_px")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.bone_reach_in_px < 0:
            raise ValueError(f"bone_reach_in_px must not be negative, got {self.bone_reach_in_px}")


@dataclass
class ExtractedContours:
    """Contour pixels (N, 2) in raw (distorted) image coordinates, and how they were found."""

    bone: np.ndarray
    pin1: np.ndarray
    pin2: np.ndarray
    diagnostics: dict = field(default_factory=dict)
    # Where a bone edge would have been kept, in cells of VISIBLE_CELL_PX raw pixels (the
    # solver's VisibleRegion once undistorted); None for contours not extracted here.
    bone_visible: np.ndarray | None = None
    # The frame's bone edges near any outline the solver asks about (raw pixels; None for
    # contours not extracted here).
    bone_edge_search: BoneEdgeSearch | None = None
    visible_cell_px: int = VISIBLE_CELL_PX  # raw pixels a side of a cell of bone_visible

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"bone": self.bone, "pin1": self.pin1, "pin2": self.pin2}

    def observation(self, view_id: str, camera: Camera,
                    undistort: Callable[[np.ndarray], np.ndarray],
                    distort: Callable[[np.ndarray], np.ndarray]) -> ViewObservation:
        """The solver's view of these contours, undistorted (``undistort`` and ``distort``
        map raw to ideal pixels and back), with what the frame hides and why a pin has no
        contour."""
        visible = None
        if self.bone_visible is not None:
            visible = VisibleRegion.from_raw(self.bone_visible, self.visible_cell_px,
                                             (camera.width, camera.height), distort)
        contours = {label: undistort(points) if len(points) else points
                    for label, points in self.as_dict().items()}
        # Where the extraction could not say which part of one bar is which pin's, the bar's
        # edges are pooled and the fit shares them out from the first solve on: pins seen one
        # behind the other (fitted whole, the bar pulls each pin towards both pins' ends), and
        # a bar with no step cut in its middle ("coincident"), as if the pins lay end to end;
        # pins exactly one behind the other cast such a bar too, each over all of it. Shared
        # by the fit, seed 3 of the phantom's scenes (pins end to end) is measured 0.13-0.33
        # deg off in CTR where its halves gave 0.40-0.42 (docs/realism.md, thirty-third pass).
        pooled, overlap = None, self.diagnostics.get("pins_overlap")
        if overlap == "behind":
            pooled = contours["pin1"]  # each pin was given the whole bar
        elif overlap == "coincident":
            both = np.vstack([contours["pin1"], contours["pin2"]])
            pooled = both[np.sort(np.unique(both, axis=0, return_index=True)[1])]  # once each, in order
        return ViewObservation(
            view_id, camera, contours, dict(self.diagnostics.get("missing", {})), visible,
            None if self.bone_edge_search is None else replace(
                self.bone_edge_search, distort=distort, undistort=undistort), pins_opaque=True,
            pin_edges=pooled)


# -- pins ----------------------------------------------------------------------------------

@dataclass
class _Bar:
    """A pin's shadow: centreline point, unit direction, half-length, half-width (px)."""

    centre: np.ndarray
    direction: np.ndarray
    half_length: float
    half_width: float

    @property
    def across(self) -> np.ndarray:
        """The unit direction across the bar (its direction turned a quarter)."""
        return np.array([-self.direction[1], self.direction[0]])

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Distance of points to the bar's rectangle outline, signed negative inside."""
        d = p - self.centre
        along = np.abs(d @ self.direction) - self.half_length
        across = np.abs(d @ self.across) - self.half_width
        outside = np.hypot(np.maximum(along, 0), np.maximum(across, 0))
        return np.where((along > 0) | (across > 0), outside, np.maximum(along, across))


def _fit_bar(p: np.ndarray) -> _Bar:
    centre = p.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((p - centre).T))
    direction = vectors[:, -1]
    along = (p - centre) @ direction
    across = (p - centre) @ np.array([-direction[1], direction[0]])
    lo, hi = np.percentile(along, [0.5, 99.5])
    centre = centre + 0.5 * (lo + hi) * direction
    # Over a filled shadow twice the median offset is the half-width, whatever small thing
    # touches its side (a lead marker's stroke made a 21 px pin 62 px wide: marker seed 15);
    # over outline points (all at the side) the top percentile is.
    half_width = min(float(np.percentile(np.abs(across), 98)), 2.0 * float(np.median(np.abs(across))))
    return _Bar(centre, direction, 0.5 * (hi - lo), half_width)


def _line_step(s: np.ndarray, o: np.ndarray, min_points: int) -> tuple[float, float] | None:
    """Where a side of a shadow steps from one straight edge to another: ``(s, step)``.

    ``o(s)`` (sorted by ``s``) is fitted by two lines split at every candidate point at once
    (prefix sums of the normal equations); the split with the least squared residual wins,
    and its step is the difference of the two lines there.
    """
    if len(s) < 2 * min_points:
        return None
    s0 = s.mean()
    x, y = s - s0, o - o.mean()
    sums = np.cumsum(np.column_stack([np.ones_like(x), x, x * x, y, x * y, y * y]), axis=0)
    head = np.vstack([np.zeros(6), sums[:-1]])  # sums over [0, i)
    tail = sums[-1] - head  # sums over [i, N)

    def fit(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, sx, sxx, sy, sxy, syy = m.T
        vx = np.maximum(sxx - sx * sx / n, 1e-9)
        cxy = sxy - sx * sy / n
        slope = cxy / vx
        return syy - sy * sy / n - cxy * slope, slope, (sy - slope * sx) / n

    split = np.arange(min_points, len(s) - min_points + 1)
    left, right = fit(head[split]), fit(tail[split])
    best = int(np.argmin(left[0] + right[0]))
    at = 0.5 * (x[split[best] - 1] + x[split[best]])
    step = (right[2][best] + right[1][best] * at) - (left[2][best] + left[1][best] * at)
    return float(at + s0), float(step)


def _bar_from_edges(s: np.ndarray, o: np.ndarray, top: np.ndarray, span: tuple[float, float],
                    centre: np.ndarray, d: np.ndarray, n: np.ndarray) -> _Bar:
    """A bar from its two edge lines (``o = a + b s`` on either side) over ``span`` of ``s``."""
    lines = [np.polyfit(s[side], o[side], 1) for side in (top, ~top)]
    mid = 0.5 * (span[0] + span[1])
    slope, offset = 0.5 * (lines[0][0] + lines[1][0]), 0.5 * (np.polyval(lines[0], mid) + np.polyval(lines[1], mid))
    direction = (d + slope * n) / np.hypot(1.0, slope)
    return _Bar(centre + mid * d + offset * n, direction, 0.5 * (span[1] - span[0]) * np.hypot(1.0, slope),
                0.5 * float(np.polyval(lines[0], mid) - np.polyval(lines[1], mid)))


_LENGTH_SHARE = 0.9  # of the other pin's length, where a pin's hidden end is inferred from it


def _split_union(edges: np.ndarray, normals: np.ndarray, min_step: float,
                 heads: np.ndarray) -> tuple[list[_Bar], str]:
    """Two bars in one shadow where the pins overlap, and how they overlap.

    The steel saturates the detector, so the overlap is no darker than either pin: only the
    outline tells them apart. Seen nearly along the resection plane the two pins line up,
    staggered along their common axis and offset across it; each long side of the union
    then steps once from one pin's edge to the other's, at the two ends of the overlap. The
    pin holding one end of the union reaches to the farther step, the other from the nearer
    step to the other end. Where only one side steps, the pin that is outward there holds it
    over the overlap, so the step is where the other pin ends or the outward one begins; the
    overlap's other end follows from the two pins' equal projected length (one model,
    parallel), kept ``_LENGTH_SHARE`` short of it for the few per cent the two differ.
    A side without a step is shared by both pins over their spans. The sides of pin heads
    (``heads``, left out of ``edges``) may say where the pins lie (:func:`_spans_from_heads`):
    where neither side steps, both pins' spans; where one does, the span of the pin whose
    inner end the step does not locate.
    """
    centre = edges.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((edges - centre).T))
    d = vectors[:, -1]
    n = np.array([-d[1], d[0]])
    s, o, facing = (edges - centre) @ d, (edges - centre) @ n, normals @ n
    long = np.abs(facing) > 0.9
    width = 2.0 * float(np.median(np.abs(o[long]))) if long.any() else 0.0
    ends = (s.min(), s.max())
    sides = long & (s > ends[0] + width) & (s < ends[1] - width)
    top = facing > 0
    steps: list[float | None] = []
    outward: list[float] = []
    for sign, side in ((1.0, sides & top), (-1.0, sides & ~top)):
        order = np.argsort(s[side])
        found = _line_step(s[side][order], o[side][order], max(5, int(width)))
        if found is not None and abs(found[1]) >= min_step:
            steps.append(found[0])
            outward.append(sign * found[1])
        else:
            steps.append(None)
            outward.append(0.0)
    known = [at for at in steps if at is not None]
    overlap = "staggered"
    by_heads = _spans_from_heads((heads - centre) @ d, ends, width)
    if not known and by_heads is not None:
        spans = by_heads
    elif not known:
        # The edges coincide. Two pins of one model project to nearly equal lengths, so the
        # middle of the union lies in their overlap: each pin owns the half beyond it.
        middle = 0.5 * (ends[0] + ends[1])
        steps, overlap = [middle, middle], "coincident"
        spans = ((ends[0], middle), (middle, ends[1]))
    elif len(known) == 1:
        # The step locates one pin's inner end; the other's is where the heads put it, else
        # inferred from the pins' alike lengths (headed pins seed 16, view 2: a step where
        # the second pin's tip leaves the first's shadow, the first pin's head on the
        # second's shaft; inferred, the first pin ended 34 px short of its head).
        k, at = (0 if steps[0] is not None else 1), known[0]
        if outward[k] > 0:  # the second pin is outward: it begins here
            end = by_heads[0][1] if by_heads is not None else ends[0] + _LENGTH_SHARE * (ends[1] - at)
            spans = ((ends[0], max(at, end)), (at, ends[1]))
        else:  # the first pin is outward: it ends here
            begin = by_heads[1][0] if by_heads is not None else ends[1] - _LENGTH_SHARE * (at - ends[0])
            spans = ((ends[0], at), (min(at, begin), ends[1]))
    else:
        spans = ((ends[0], max(known)), (min(known), ends[1]))
    # On a side with a step a pin owns its part of that side; without one, the two pins'
    # edges coincide there and each owns the side over its span.
    mine = []
    for k, span in enumerate(spans):
        on = [(s < b if k == 0 else s >= b) if b is not None else (s >= span[0]) & (s <= span[1])
              for b in steps]
        mine.append(sides & np.where(top, on[0], on[1]))
    if min(min((m & top).sum(), (m & ~top).sum()) for m in mine) < 2:
        bar = _fit_bar(edges)  # too short to tell (seen end-on): both pins share the outline
        return [bar, bar], "unresolved"
    return [_bar_from_edges(s[m], o[m], top[m], span, centre, d, n) for m, span in zip(mine, spans)], overlap


def _spans_from_heads(heads: np.ndarray, ends: tuple[float, float], width: float
                      ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The spans along a union of two pins in line whose sides do not step, from where its
    pin heads lie (``heads``: their side points' offsets along it), or None.

    A head is on a pin's outer end, and the two pins of a block point the same way. With
    one head at an end of the union and another on its shaft, the second head is where the
    pin in front begins: it reaches to the union's other end, and the pin behind it, whose
    head is the first, is as long (``_LENGTH_SHARE`` of it). Headed pins seed 3, view 1:
    split in the middle instead, the first pin was cut 60 px short and the case refused."""
    near = _HEAD_MOST_WIDTHS * width  # a head's run is no longer
    at_start, at_end = heads <= ends[0] + near, heads >= ends[1] - near
    inner = heads[~at_start & ~at_end]
    if not inner.size or np.ptp(inner) > near or bool(at_start.any()) == bool(at_end.any()):
        return None
    if at_start.any():  # the pins point towards the union's far end
        begin = float(inner.min())
        return (ends[0], max(begin, ends[0] + _LENGTH_SHARE * (ends[1] - begin))), (begin, ends[1])
    begin = float(inner.max())
    return (ends[0], begin), (min(begin, ends[1] - _LENGTH_SHARE * (begin - ends[0])), ends[1])


_HEAD_MARGIN_PX = 3.0
_HEAD_MARGIN_SHARE = 0.2  # of the shaft's width: how far a head stands out of each side, at least
_HEAD_MOST_WIDTHS = 3.0  # of the shaft's width: the longest run of a bar's sides taken for a head


def _head_sides(edges: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Which of one shadow's edge points lie on the sides of a pin's head (True).

    A head (the plan's pin model has none) stands out of *both* sides of the shaft at once,
    over a short run of its length, and each side comes back to where it was on either end
    (or on its one end, at the shadow's end): a bump of each side, shorter than
    ``_HEAD_MOST_WIDTHS`` widths and at least the margin above that side's own level on
    both of its neighbours. Where two pins in line overlap, offset across, the union
    widens over a short run too (real surgeon's views seed 10, view 1: 70 px), but each
    side steps once and stays out: no bump, and that step is the split's evidence. A head
    left on the sides is read as such a step: headed pins seed 3, view 1 (two pins in line,
    the second pin's head on the first pin's shaft) was split there and its first pin cut
    to a third of its length.

    Each side's level is its own on either end of the bump, not one for the whole side:
    with the pins offset across, a head at the union's end stands out of its own pin's
    side but hardly of the other pin's, further out (headed pins seed 16, view 1: read as
    a step, the first pin was cut at the second's head, half its length). A head standing
    out of one side only (the second pin's, offset across) is where that pin begins, a
    step: it is left on the sides (left out, the step was placed mid-way across it, 28 px
    into the pin: headed pins seed 9, view 1).
    """
    bar = _fit_bar(edges)
    s, o = (edges - bar.centre) @ bar.direction, (edges - bar.centre) @ bar.across
    # The long sides, facing out: a notch's or a slit's inner sides are no head's (real
    # tibia's headed pins seed 6, view 2: mixed into one side's level, they made a bump of
    # it over the first pin's head, and the head was taken for both sides' and cut out).
    facing = normals @ bar.across
    top, bottom = (facing > 0.9) & (o > 0), (facing < -0.9) & (o < 0)
    if np.count_nonzero(top) < _MIN_PIN_EDGES or np.count_nonzero(bottom) < _MIN_PIN_EDGES:
        return np.zeros(len(edges), bool)
    width = float(np.median(o[top]) - np.median(o[bottom]))
    margin = max(_HEAD_MARGIN_PX, _HEAD_MARGIN_SHARE * width)
    step = max(0.5 * width, 1.0)
    bins = ((s - s.min()) / step).astype(int)
    count = int(bins.max()) + 1
    # An opening of each side's level (outward positive) by a run longer than a head
    # removes its bumps and keeps its steps: what the side is where it has no head.
    window = int(_HEAD_MOST_WIDTHS * width / step) + 1
    head_bins = np.ones(count, bool)
    for side, sign in ((top, 1.0), (bottom, -1.0)):
        total = np.bincount(bins[side], minlength=count)
        seen = total > 0
        level = np.bincount(bins[side], sign * o[side], minlength=count)[seen] / total[seen]
        level = np.interp(np.arange(count), np.flatnonzero(seen), level)
        shaft = ndimage.grey_opening(level, size=window, mode="constant", cval=-np.inf)
        head_bins &= level > shaft + margin
    return (top | bottom) & head_bins[bins]


_PIN_EDGE_REACH_PX = 6.0  # an edge this far from both pins' bars belongs to another shadow
# The two pins of a block are parallel and alike: two shadows are taken as the pair only
# when this close in direction and width; of several such pairs, the closest.
_PIN_CANDIDATES = 6
_PAIR_MAX_ANGLE_DEG = 8.0
_PAIR_MAX_WIDTH_RATIO = 1.4


# How far (px) pins are commonly found from their centres projected at the initial pose
# (encoder set-up error: ~6 deg and 20 mm at level 1, ~150 px at the pins).
_EXPECTED_PIN_SPREAD_PX = 150.0


def _robust_width(bar: _Bar, points: np.ndarray) -> float:
    across = (points - bar.centre) @ bar.across
    return 4.0 * float(np.median(np.abs(across)))


# A pin's shadow is bounded by two straight lines. The dark band that a C-arm's unsharp
# masking leaves along a bone's edge (the plateau, a cortex) is as wide and as long, but
# follows the bone's curve: its sides lie a median 1.2-3.9 px from their lines where a
# single pin's lie within 0.5 px, even where its mask bulges into a bone's edge over a
# part of its length (processing seeds 0, 2, 10, 11, 19, 27), and 0.9 px where it crosses
# a retractor blade (retractors seed 26). Asked of parallel pairs only: pins seen nearly
# end-on are short and their heads hold much of them, and a converging pair has tests of
# its own (operating-room seed 8).
_PIN_SIDE_WANDER_PX = 1.0
_SIDE_SLICE_PX = 3.0  # the sides are read in slices this long across the bar
_SIDE_SPAN = 0.8  # of the bar's length, about its centre: a head on an end is left out


def _side_wander(bar: _Bar, pixels: np.ndarray) -> float:
    """How far (median px) the wavier long side of a shadow's pixels lies from its line."""
    along, across = (pixels - bar.centre) @ bar.direction, (pixels - bar.centre) @ bar.across
    inner = np.abs(along) < _SIDE_SPAN * bar.half_length
    if np.count_nonzero(inner) < 2:
        return 0.0
    slices = ((along[inner] + bar.half_length) / _SIDE_SLICE_PX).astype(int)
    low, high = np.full(slices.max() + 1, np.inf), np.full(slices.max() + 1, -np.inf)
    np.minimum.at(low, slices, across[inner])
    np.maximum.at(high, slices, across[inner])
    seen = np.flatnonzero(np.isfinite(low))
    if len(seen) < 4:
        return 0.0
    # Each side's line passes through the medians of its two halves: a head wider than the
    # shaft, or a bulge into a bone's edge, holds less than half of either.
    half = seen < np.median(seen)
    wander = 0.0
    for side in (low[seen], high[seen]):
        (x0, y0), (x1, y1) = ((float(np.median(seen[part])), float(np.median(side[part])))
                              for part in (half, ~half))
        line = y0 + (seen - x0) * (y1 - y0) / max(x1 - x0, 1e-9)
        wander = max(wander, float(np.median(np.abs(side - line))))
    return wander


def _parallel_pair(fitted: list[tuple[_Bar, np.ndarray]], widths: _PinWidths,
                   expected: np.ndarray | None = None, least_length: float = 0.0,
                   converging: bool = False) -> tuple[int, int] | None:
    """The two shadows most alike in direction and width (the block's parallel pins), or
    None when no two are alike enough to be the pins. With ``expected`` pin centres (the
    initial pose's projection), a pair far from them costs more: a retractor blade seen
    edge-on is as straight as a pin, but not where the plan puts the pins. Shadows shorter
    than ``least_length`` are no pin's (a bent blade's fold is as wide, but short).
    ``converging``: the two pins seen nearly end-on instead, pointing at their vanishing
    point (:func:`_converging`), stubs among them."""
    best, best_cost = None, np.inf
    widths_px = [_robust_width(bar, points) for bar, points in fitted]
    long = [2.0 * bar.half_length >= least_length for bar, _ in fitted]
    straight = [_side_wander(bar, points) <= _PIN_SIDE_WANDER_PX for bar, points in fitted]
    stub = [2.0 * bar.half_length < _PIN_ELONGATION * width for (bar, _), width in zip(fitted, widths_px)]
    where = None if expected is None else np.asarray(expected, float).reshape(2, 2)
    for i in range(len(fitted)):
        for j in range(i + 1, len(fitted)):
            if not (long[i] and long[j]):
                continue
            cos = abs(float(fitted[i][0].direction @ fitted[j][0].direction))
            angle = float(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))))
            ratio = max(widths_px[i], widths_px[j]) / max(min(widths_px[i], widths_px[j]), 1e-9)
            if (ratio > _PAIR_MAX_WIDTH_RATIO
                    or not (widths.one_pin(widths_px[i]) and widths.one_pin(widths_px[j]))):
                continue
            a, b = fitted[i][0], fitted[j][0]
            # Across for parallel bars (pins in line lie far apart along), between the
            # centres for converging ones (a stub's axis says little).
            apart = np.linalg.norm(b.centre - a.centre) if converging else _off_axis(a, b)
            if apart > widths.pair_apart_most:
                continue
            if converging:
                unlike = _converging(a, b, 0.5 * (widths_px[i] + widths_px[j]))
                if unlike is None:
                    continue
                bent = 1.0 + unlike
            elif angle <= _PAIR_MAX_ANGLE_DEG and not (stub[i] or stub[j]):
                if not (straight[i] and straight[j]):
                    continue  # bands along a bone's edge, side by side, not pins
                bent = angle / _PAIR_MAX_ANGLE_DEG
            else:
                continue
            cost = bent + np.log(ratio) / np.log(_PAIR_MAX_WIDTH_RATIO)
            if where is not None:
                off = min(np.linalg.norm(a.centre - where[0]) + np.linalg.norm(b.centre - where[1]),
                          np.linalg.norm(a.centre - where[1]) + np.linalg.norm(b.centre - where[0]))
                cost += 0.5 * off / _EXPECTED_PIN_SPREAD_PX
            if cost < best_cost:
                best, best_cost = (i, j), cost
    return best


# Parallel pins seen nearly end-on converge in projection towards their vanishing point:
# seen along 10-30 deg of their axis, two pins 50 mm apart are 30-40 deg from parallel on
# the frame (operating-room seeds 8, 24: short shadows with heads). Such a pair is taken
# when the two shadows point at one vanishing point beyond both, within this angle, and
# are foreshortened alike. A pin from depth z along its axis d, of length l, casts a shaft
# whose length over its far end's distance to the vanishing point is l d_z / (z + l d_z):
# the same for both pins of a block, alike in length and depth (views seeds 17, 24, 26,
# view 1: 0.14 and 0.14 at the true poses), while their distances to it are not (328 and
# 452 px, 401 and 231: they depend on where each pin lies across the beam). The shaft is
# the shadow less a pin's width (its end discs, seen nearly face-on, add about that).
_CONVERGING_MAX_ANGLE_DEG = 45.0
_CONVERGING_MAX_SHARE = 0.35  # a shaft's length over its distance to the vanishing point
_CONVERGING_MAX_RATIO = 1.3  # between the two pins' shares


def _converging(a: _Bar, b: _Bar, width_px: float) -> float | None:
    """How unlike two parallel pins' shadows of ``width_px`` converging on their vanishing
    point the bars are (0 alike, 1 at the limit), or None when they cannot be such a pair."""
    cos = float(a.direction @ b.direction)
    if np.degrees(np.arccos(np.clip(abs(cos), 0.0, 1.0))) > _CONVERGING_MAX_ANGLE_DEG:
        return None
    if abs(a.direction[0] * b.direction[1] - a.direction[1] * b.direction[0]) < 1e-6:
        return None  # parallel on the frame: no vanishing point to point at
    # Where the axes meet: a.centre + s a.direction = b.centre + t b.direction.
    s, t = np.linalg.solve(np.column_stack([a.direction, -b.direction]), b.centre - a.centre)
    if abs(s) <= a.half_length or abs(t) <= b.half_length:
        return None  # the axes cross inside a shadow: no vanishing point beyond both
    to_a, to_b = -s * a.direction, -t * b.direction  # from the vanishing point to each centre
    if float(to_a @ to_b) <= 0.0:
        return None  # the shadows lie on either side of it: they diverge
    halves = np.array([a.half_length, b.half_length])
    shafts = np.maximum(2.0 * halves - width_px, 1.0)
    shares = shafts / (np.abs([s, t]) + 0.5 * shafts)  # over its far end's distance
    unlike = float(np.log(shares.max() / shares.min()) / np.log(_CONVERGING_MAX_RATIO))
    if shares.max() > _CONVERGING_MAX_SHARE or unlike > 1.0:
        return None
    return unlike


def _without_head(edges: np.ndarray, bar: _Bar) -> np.ndarray:
    """A pin's edge points without those of a head wider than its shaft (the plan's pin
    model has none): points further from the axis than the shaft's edges by a margin."""
    if len(edges) < _MIN_PIN_EDGES:
        return edges
    across = np.abs((edges - bar.centre) @ bar.across)
    return edges[across <= np.median(across) + _HEAD_MARGIN_PX]


def _order_pins(bars: list[_Bar], config: ContourConfig, expected: np.ndarray | None) -> list[_Bar]:
    if expected is not None:
        expected = np.asarray(expected, float).reshape(2, 2)
        cost = [np.linalg.norm(bars[0].centre - expected[0]) + np.linalg.norm(bars[1].centre - expected[1]),
                np.linalg.norm(bars[0].centre - expected[1]) + np.linalg.norm(bars[1].centre - expected[0])]
        # The initial pose is off by ~150 px at the pins: only a clear difference decides;
        # otherwise the rule (6 of 102 simulated operating-room frames were labelled
        # wrongly by a narrow margin of the expected centres, right by the rule).
        if abs(cost[0] - cost[1]) >= _EXPECTED_PIN_SPREAD_PX:
            return bars if cost[0] <= cost[1] else bars[::-1]
    axis = bars[0].direction + np.sign(bars[0].direction @ bars[1].direction) * bars[1].direction
    axis = axis * (1 if axis[0] >= 0 else -1)
    first = bars if bars[0].centre @ axis <= bars[1].centre @ axis else bars[::-1]
    return first if config.pin_order == "left_to_right" else first[::-1]


_MIN_PIN_EDGES = 20  # fewer edge points than this are no pin shadow
# The plan's pin projected at the initial pose gives its shadow's length only roughly (at a
# level-1 pose 0.57-2.2 times the true one: the foreshortening of a pin at a steep angle
# changes fast with the pose); a shadow shorter than this share of it is not a pin (a bent
# blade's fold seen obliquely is as wide as a pin and as straight, but 0.17-0.32 of it).
_PIN_LENGTH_SHARE = 0.4
# A pin's shadow (or two overlapping along their axis) is a straight bar: this much longer
# than wide, filling this share of its rectangle. Retractor blades, collimator blades,
# lead letters and a femur's end-on shaft are wider, shorter or not straight.
_PIN_ELONGATION = 3.0
# A pin seen nearly end-on casts a stub, a pill 1.5-3 times as long as wide (views seed 24,
# view 1, 4 deg from AP: 2.3 and 3.4). Split as a crossed shadow, its straight piece came
# out thinner than the pin (14 px of 22) and was not paired: a stub is a candidate of its
# own, paired only as one of two converging pins (_converging), never as a parallel bar.
_STUB_ELONGATION = 1.5
_PIN_FILL = 0.7
_PIN_UNION_WIDTH = 1.8  # two pins side by side: at most this many widths wide
_PIN_GROW_TO = 0.8  # excess to which an unscattered steel shadow is grown
_PIN_PEAK_SHARE = 0.5  # of the strongest bar's median excess, that another bar must reach


# With the plan's pin projected at the initial pose, a shadow's width is known to about
# 10% (the pose's depth error): a pin's is within these shares of it, two pins side by
# side at most the last. A retractor blade seen edge-on (2 mm) or a strip of a face-on
# blade is as straight as a pin but rarely as wide. A bar is taken for two pins seen one
# behind the other only when wider than the fourth share: one pin's shadow, its partner
# missed, must not be fitted as both (each pin's line would then lie in that bar's plane).
_EXPECTED_WIDTH_SHARES = (0.65, 1.5, 2.1, 1.2)
# A block's two pins lie 20-40 mm apart (the simulator's range; a block's holes are rarely
# 50 mm apart), in the tibia: at the true poses of 720 views (both models; idealised,
# surgeon's and operating-room seeds 0-59) their shadows' axes lay at most 11 pin widths
# apart across, and their centres 12.6. Two shadows further apart than this many widths
# are not the pair (18 widths: 58 mm of 3.2 mm pins). Operating-room seed 4, view 1 (AP):
# two retractor blades seen edge-on either side of the plateau, 26 widths apart, parallel
# and a pin wide, were taken for the pins, which showed as stubs between them.
_PAIR_MOST_APART_WIDTHS = 18.0


@dataclass(frozen=True)
class _PinWidths:
    """Widths (px) of a pin's shadow: one pin's least and most, two side by side's most, and
    the least of two seen one behind the other."""

    least: float
    most: float
    union_most: float
    least_behind: float  # two pins seen one behind the other: at least this wide
    pair_apart_most: float  # the two pins' shadows: their axes at most this far apart

    @staticmethod
    def of(config: ContourConfig, expected_px: float | None) -> _PinWidths:
        if expected_px is None:
            lo, hi = config.pin_width_px
            return _PinWidths(lo, hi, _PIN_UNION_WIDTH * hi, hi, _PAIR_MOST_APART_WIDTHS * 0.5 * (lo + hi))
        least, most, union_most, least_behind = (share * expected_px for share in _EXPECTED_WIDTH_SHARES)
        return _PinWidths(least, most, union_most, least_behind, _PAIR_MOST_APART_WIDTHS * expected_px)

    def one_pin(self, width: float) -> bool:
        return self.least <= width <= self.most

    def two_behind(self, width: float) -> bool:
        return self.least_behind < width <= self.union_most


def _shape_of(pixels: np.ndarray, widths: _PinWidths, config: ContourConfig) -> str | None:
    """What ``pixels`` (N, 2) are shaped like: "bar" (a pin's shadow, or two pins' overlap),
    "stub" (one pin's seen nearly end-on: a filled pill one pin wide, shorter than a bar)
    or None."""
    if len(pixels) < config.pin_min_area_px:
        return None
    bar = _fit_bar(pixels)
    # Across a filled bar offsets are uniform: four times their median is its width,
    # whatever a head on its end adds.
    width, length = _robust_width(bar, pixels), 2.0 * bar.half_length
    if len(pixels) < _PIN_FILL * width * length:
        return None
    if widths.least <= width <= widths.union_most and length >= _PIN_ELONGATION * width:
        return "bar"
    if widths.one_pin(width) and length >= _STUB_ELONGATION * width:
        return "stub"
    return None


def _bar_shaped(pixels: np.ndarray, widths: _PinWidths, config: ContourConfig) -> bool:
    """Whether ``pixels`` (N, 2) are shaped like a pin's shadow (or two pins' overlap)."""
    return _shape_of(pixels, widths, config) == "bar"


# A shadow lying this much under a collimator shutter is no pin's: a C-arm's edge enhancement
# leaves a dark band along a shutter's edge, as straight and as wide as a pin (operating-room
# seed 6, view 1: 782 px long, 21 px wide, taken for both pins while the pins were missed).
_MOST_UNDER_SHUTTER = 0.5


def _under_shutters(labels: np.ndarray, count: int, shutters: np.ndarray) -> np.ndarray:
    """Which components of ``labels`` lie mostly under the collimator ``shutters`` (a mask)."""
    if not shutters.any():
        return np.zeros(count, bool)
    inside = np.bincount(labels[shutters], minlength=count)[:count]
    area = np.bincount(labels.ravel(), minlength=count)[:count]
    return inside > _MOST_UNDER_SHUTTER * np.maximum(area, 1)


def _steel_level(levels: np.ndarray) -> float:
    """The typical excess of steel in the frame, from its bars' (``levels``): the strongest
    bar's, unless it stands alone far above two bars alike, the pins (a retractor blade seen
    edge-on is 15-20 mm of steel against a pin's 3-4 mm: operating-room seed 25, 4.9
    against the pins' 1.8 and 1.9)."""
    order = np.sort(levels)[::-1]
    for level, below in zip(order[:-1], order[1:]):
        if level < order[0] / 3.0:
            break
        if below >= level / 1.5:
            return float(level)
    return float(order[0])


def _pin_like(labels: np.ndarray, count: int, widths: _PinWidths, config: ContourConfig
              ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Which components of ``labels`` are shaped like a pin's shadow (or two pins' overlap),
    and the pixels of each shaped like a stub (:func:`_shape_of`)."""
    ok, stubs = np.zeros(count, bool), {}
    for label, pixels in _pixels_of(labels, np.arange(count) > 0).items():
        shape = _shape_of(pixels, widths, config)
        ok[label] = shape == "bar"
        if shape == "stub":
            stubs[label] = pixels
    return ok, stubs


def _steel_stubs(stubs: list[np.ndarray], excess: np.ndarray, level: float | None) -> list[np.ndarray]:
    """The ``stubs`` (pixels of each) whose typical excess is steel's, at ``level`` (the
    bars'; with none, the strongest stubs' own)."""
    if not stubs:
        return stubs
    typical = np.array([float(np.median(excess[p[:, 1].astype(int), p[:, 0].astype(int)])) for p in stubs])
    level = _steel_level(typical) if level is None else level
    return [pixels for pixels, value in zip(stubs, typical) if value >= _PIN_PEAK_SHARE * level]


def _outline_edges(mask: np.ndarray, grad: tuple[np.ndarray, np.ndarray], config: ContourConfig
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Edge points (and normals) of the steel shadows of ``mask``, placed on ``grad`` (the
    transmitted intensity's gradient)."""
    points, normals = outline_with_normals(mask, 10)
    edges, normals, _, _ = edges_along_normals(grad, points, normals, config.edge_search_px,
                                                config.min_edge_strength)
    return edges + config.pin_edge_offset_px * normals, normals


def _pixels_of(labels: np.ndarray, chosen: np.ndarray) -> dict[int, np.ndarray]:
    """The pixels (N, 2: column, row) of each label that ``chosen`` (by label) marks, from
    one pass over the frame (a mask per label costs a pass each)."""
    ys, xs = np.nonzero(chosen[labels])
    which = labels[ys, xs]
    order = np.argsort(which, kind="stable")
    pixels = np.column_stack([xs[order], ys[order]]).astype(float)
    labelled = np.flatnonzero(chosen)
    bounds = np.searchsorted(which[order], np.append(labelled, labelled[-1] + 1) if len(labelled) else [])
    return {int(label): pixels[bounds[k]:bounds[k + 1]] for k, label in enumerate(labelled)}


_LINE_ANGLES_DEG = np.arange(0.0, 180.0, 10.0)
_CROSSED_PIECES = 4  # straight bars taken out of one crossed shadow at most
_PIECE_OVERLAP = 0.3  # share of a piece that may lie in a piece already taken


def _line(length: int, angle_deg: float) -> np.ndarray:
    """A one-pixel line of ``length`` (odd) at ``angle_deg``: a structuring element."""
    kernel = np.zeros((length, length), np.uint8)
    c = (length - 1) / 2.0
    t = np.linspace(-c, c, 2 * length)
    a = np.radians(angle_deg)
    kernel[np.round(c + t * np.sin(a)).astype(int), np.round(c + t * np.cos(a)).astype(int)] = 1
    return kernel


def _straight_pieces(shadow: np.ndarray, widths: _PinWidths, config: ContourConfig
                     ) -> list[np.ndarray]:
    """Pin-shaped straight bars inside a steel shadow that is not one bar (a pin crossed or
    touched by a retractor blade seen edge-on, both pins across one blade), as pixel masks
    of ``shadow``'s shape: what survives an opening by a line longer than any crossing
    bar is wide, in the direction of the bar, taken greedily from the largest. A shadow a
    pixel thin holds none, and has no half size (a real tibia's operating-room frame had one)."""
    if min(shadow.shape) < 2:
        return []
    half = cv2.resize(shadow.astype(np.uint8), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_NEAREST)
    length = int(config.pin_width_px[1]) | 1  # twice the widest pin, at half size
    pieces: list[tuple[int, np.ndarray, int]] = []  # (area, labels, label) at half size
    for angle in _LINE_ANGLES_DEG:
        opened = cv2.morphologyEx(half, cv2.MORPH_OPEN, _line(length, angle))
        count, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
        pieces += [(int(stats[k, cv2.CC_STAT_AREA]), labels, k) for k in range(1, count)]
    pieces.sort(key=lambda p: -p[0])
    taken: list[np.ndarray] = []
    found: list[np.ndarray] = []
    for area, labels, k in pieces:
        if len(found) == _CROSSED_PIECES or 4 * area < config.pin_min_area_px:
            break
        piece = labels == k
        if any((piece & other).sum() > _PIECE_OVERLAP * area for other in taken):
            continue
        full = shadow & (cv2.resize(piece.astype(np.uint8), shadow.shape[::-1],
                                    interpolation=cv2.INTER_NEAREST) > 0)
        ys, xs = np.nonzero(full)
        if _bar_shaped(np.column_stack([xs, ys]).astype(float), widths, config):
            taken.append(piece)
            found.append(full)
    return found


def _split_crossed(labels: np.ndarray, stats: np.ndarray, good: np.ndarray, widths: _PinWidths,
                   config: ContourConfig) -> tuple[int, np.ndarray]:
    """Relabel, in place, the straight pin-shaped pieces of each shadow that is not one bar
    as shadows of their own; returns the new count of labels and which are pin-like.

    A shadow with two such pieces is split even if it passed as pin-like: a short pin
    across a long blade seen edge-on is still much longer than wide."""
    count = len(good)
    good = good.copy()
    added: list[bool] = []
    # The least pin-shaped bar: one pin's least width, as long as a pin must be, filled.
    least_length = _PIN_ELONGATION * widths.least
    least_area = max(2 * config.pin_min_area_px, _PIN_FILL * least_length * widths.least)
    for label in range(1, count):
        x, y, w, h, area = stats[label]
        if area < least_area or max(w, h) < least_length:
            continue
        window = labels[y:y + h, x:x + w]
        pieces = _straight_pieces(window == label, widths, config)
        if len(pieces) < (1 if not good[label] else 2):
            continue
        good[label] = False
        for piece in pieces:
            window[piece] = count + len(added)
            added.append(True)
    return count + len(added), np.concatenate([good, np.asarray(added, bool)])


def _split_notched(labels: np.ndarray, mask: np.ndarray, count: int, good: np.ndarray,
                   widths: _PinWidths, config: ContourConfig) -> int:
    """Relabel, in place, each pin-like (``good``) shadow of ``mask`` that is two parallel
    bars joined at one end as two shadows (the cut left out of ``mask``); returns the new
    count of labels.

    Two pins side by side a few px apart are two shadows, but where one's head (or the
    blur of their edges) touches the other's shaft they are one, notched from the other
    end by the slit between them. Read as two pins overlapping in line, its outline has
    four long sides where the split expects two (headed pins seed 7, view 2: one pin cut
    to 130 of its 380 px; idealised seed 25, view 2: pins touching in a slit a pixel or
    two wide, one cut to half its length). The notch is what a closing by a pin's least
    width adds to the shadow; where it is as long as a pin must be and runs along the
    shadow, the shadow is cut along the notch's axis, and taken as two where both sides
    are bars. A slit shows only once the mask is opened: ``mask`` is."""
    size = int(widths.least) | 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    least_length = _PIN_ELONGATION * widths.least
    head_length = 2.0 * widths.most  # what joins them: a head at most (3 foreseen widths long)
    parallel = np.cos(np.radians(_PAIR_MAX_ANGLE_DEG))
    h, w = labels.shape
    for label, pixels in _pixels_of(labels, good).items():
        (x0, y0), (x1, y1) = pixels.min(axis=0).astype(int) - size, pixels.max(axis=0).astype(int) + size + 1
        x0, y0 = max(x0, 0), max(y0, 0)
        window = labels[y0:min(y1, h), x0:min(x1, w)]
        shown = mask[y0:min(y1, h), x0:min(x1, w)]
        shadow = ((window == label) & shown).astype(np.uint8)
        notch = (cv2.morphologyEx(shadow, cv2.MORPH_CLOSE, disk) > 0) & (shadow == 0)
        found, notches, stats, _ = cv2.connectedComponentsWithStats(notch.astype(np.uint8), connectivity=8)
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) if found > 1 else 0
        # A slit a pixel wide has as many pixels as it is long: fewer, it is too short.
        if not largest or stats[largest, cv2.CC_STAT_AREA] < least_length:
            continue
        ys, xs = np.nonzero(notches == largest)
        slit = _fit_bar(np.column_stack([xs, ys]).astype(float))
        bar = _fit_bar(pixels)
        if 2.0 * slit.half_length < least_length or abs(slit.direction @ bar.direction) < parallel:
            continue
        # The cut: the notch's axis, on through what joins the two bars (a head at most).
        ys, xs = np.nonzero(shadow)
        offset = np.column_stack([xs, ys]) - slit.centre
        cut = ((np.abs(offset @ slit.across) <= 1.0)
               & (np.abs(offset @ slit.direction) <= slit.half_length + head_length))
        shadow[ys[cut], xs[cut]] = 0
        found, parts, stats, _ = cv2.connectedComponentsWithStats(shadow, connectivity=4)
        if found < 3:
            continue
        first, second = 1 + np.argsort(stats[1:, cv2.CC_STAT_AREA])[::-1][:2]
        if not all(_bar_shaped(np.argwhere(parts == part)[:, ::-1].astype(float), widths, config)
                   for part in (first, second)):
            continue
        shown[(window == label) & (parts != first) & (parts != second)] = False  # the cut is no one's
        window[parts == second] = count
        count += 1
    return count


def _below_pins(A: np.ndarray, broad: np.ndarray, config: ContourConfig) -> np.ndarray:
    """What the frame would show without its pins: ``A``'s 100-px median (the tissue and
    bone around a pin), and on and beside broad metal ``A`` opened (half size) by a disk
    wider than a pin: the opening keeps what is broader than a pin, so a pin crossing a
    face-on retractor blade stands out over the blade as over tissue, and the blade itself
    is no pin's shadow (the median there is raised by the blade). The opening everywhere
    moved pins' edges: it is the lower envelope of a sloping background, and a step where
    a pin leaves the bone split two overlapping pins in the wrong places (shutters seed
    19, 1.2 deg off)."""
    small = cv2.resize(A, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(small, [0.5, 99.5])
    quantised = np.clip((small - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    median = cv2.medianBlur(quantised, 25).astype(np.float32) / 255 * (hi - lo) + lo
    shape = A.shape[::-1]
    median = cv2.resize(median, shape, interpolation=cv2.INTER_LINEAR)
    if not broad.any():
        return median
    half = cv2.GaussianBlur(cv2.resize(A, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA),
                            (0, 0), 1.0)
    size = int(config.pin_width_px[1] / 2) | 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    opened = np.minimum(cv2.resize(cv2.morphologyEx(half, cv2.MORPH_OPEN, disk), shape,
                                   interpolation=cv2.INTER_LINEAR), A)
    beside = cv2.dilate(broad.astype(np.uint8), np.ones((2 * size + 1,) * 2, np.uint8)) > 0
    return np.where(beside, opened, median)


def _split_one(labels: np.ndarray, shadows: np.ndarray, edges: np.ndarray, normals: np.ndarray,
               widths: _PinWidths, least_length: float, config: ContourConfig, stepped_only: bool = False
               ) -> tuple[list[_Bar], str, np.ndarray] | str | None:
    """When no two shadows are the pins, the one that holds both: of the candidates, largest
    first, the first that splits into two bars no wider than a pin on average (a strip of a
    retractor blade does not) and each as long as a pin can be (``least_length``: one pin's
    shadow with no step on its sides, the other pin missed, is not cut into two half pins;
    patella seeds 0 and 12 at level 3 were measured 2.0 and 10.7 deg off so), with its
    bars, how they overlap and its edge points. All are tried: two pins in line across
    three blades are a smaller shadow than the blades' strips (retractors seed 22, view 2).
    The sides of pin heads are left out first (``_head_sides``): a head is no step between
    two pins.

    If none splits, a bar clearly wider than one pin but no wider than two side by side,
    alike along its length, is the pins seen one behind the other (a lateral view: views
    seeds 5 and 15, view 2: 32-33 px in each third). Its edges cannot be told apart here,
    so both pins get all of them ("behind") for the fit to share out
    (:meth:`JointProblem.with_pin_edges_shared`). Pins in line, one overlapping the other's
    end, are wider only where they overlap (the real tibia's operating-room seed 26 at
    level 3, between two blades: 44, 34 and 16 px; taken for both pins it was measured 5 deg
    off). Where none is taken, what was seen, for the refusal's words: ``ONE_BAR_TWO_WIDE``
    where a bar was of that width on average (the pins overlap there), else
    ``ONE_BAR_ONE_WIDE`` where a straight bar one pin wide was as long as a pin (the pins
    exactly one behind the other, or one hidden: surgeon's views seed 19, view 2, a lateral
    view), else None. ``stepped_only``: only a split that steps on the sides or heads locate
    ("staggered") into two bars each a pin wide is taken (a piece of two pins' union between
    blades, one part as wide as both, split so, measured operating-room seed 23 8 deg off,
    refused only by a fit gate at its limit)."""
    h, w = labels.shape
    at = np.clip(np.round(edges).astype(int), 0, [w - 1, h - 1])
    behind: tuple[list[_Bar], str, np.ndarray] | None = None
    seen: str | None = None
    for shadow in shadows:
        in_shadow = labels == shadow
        own = cv2.dilate(in_shadow.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        mine = own[at[:, 1], at[:, 0]]
        if np.count_nonzero(mine) < _MIN_PIN_EDGES:
            continue
        heads = _head_sides(edges[mine], normals[mine])
        head_points = edges[mine][heads]
        mine[mine] = ~heads
        bars, overlap = _split_union(edges[mine], normals[mine], config.pin_min_step_px, head_points)
        bar_widths = [_edge_width(bar, edges[mine]) for bar in bars]
        stepped = overlap == "staggered" and all(map(widths.one_pin, bar_widths))
        if (float(np.mean(bar_widths)) <= widths.most and min(2.0 * bar.half_length for bar in bars) >= least_length
                and (stepped or not stepped_only)):
            return bars, overlap, edges[mine]
        whole = _fit_bar(edges[mine])
        whole_width = _edge_width(whole, edges[mine])
        if seen is None and widths.one_pin(whole_width) and 2.0 * whole.half_length >= least_length:
            pixels = np.argwhere(in_shadow)[:, ::-1].astype(float)
            if _side_wander(whole, pixels) <= _PIN_SIDE_WANDER_PX:
                seen = ONE_BAR_ONE_WIDE
        if behind is None and widths.two_behind(whole_width):
            seen = ONE_BAR_TWO_WIDE
            thirds = _widths_along(whole, edges[mine])
            if (2.0 * whole.half_length >= least_length and all(widths.two_behind(w) for w in thirds)
                    and thirds.max() <= _BEHIND_EVENNESS * thirds.min()):
                behind = [whole, whole], "behind", edges[mine]
    return behind if behind is not None else seen


# What one bar that is not taken for the pins says of them (ExtractedContours.diagnostics'
# "pins_one_bar", for the refusal's words).
ONE_BAR_TWO_WIDE = "as wide as both pins"
ONE_BAR_ONE_WIDE = "one pin wide"


# Two pins one behind the other are as wide all along: the widest third of their bar's
# sides at most this many times the narrowest (1.01 on views seeds 5 and 15).
_BEHIND_EVENNESS = 1.2


def _widths_along(bar: _Bar, edges: np.ndarray) -> np.ndarray:
    """The width of ``bar`` from its edge points in each third of its sides (its ends left
    out), NaN where a third has none."""
    along, across, on_sides = _on_sides(bar, edges)
    bounds = np.array([-0.8, -0.27, 0.27, 0.8]) * bar.half_length
    return np.array([2.0 * float(np.median(across[m])) if m.any() else np.nan
                     for m in (on_sides & (along >= a) & (along < b) for a, b in zip(bounds[:-1], bounds[1:]))])


def _edge_width(bar: _Bar, edges: np.ndarray) -> float:
    """The width of ``bar`` from the edge points along its sides (a head on its end, wider,
    holds few of them)."""
    along, across, on_sides = _on_sides(bar, edges)
    sides = across[on_sides & (np.abs(along) <= bar.half_length)]
    return 2.0 * float(np.median(sides)) if len(sides) else 2.0 * bar.half_width


def _on_sides(bar: _Bar, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge point's signed offset along ``bar`` and distance across it, and whether it
    lies on a side (within twice the bar's half width of its axis)."""
    along = (edges - bar.centre) @ bar.direction
    across = np.abs((edges - bar.centre) @ bar.across)
    return along, across, across <= 2.0 * bar.half_width


def _medians(values: np.ndarray, labels: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The median of ``values`` over each label that ``chosen`` (by label) marks, 0 for the
    others: one sort of their pixels by label and value (scipy's per-label median took
    0.2 s a frame)."""
    inside = chosen[labels]
    which, value = labels[inside], values[inside]
    order = np.lexsort((value, which))
    which, value = which[order], value[order]
    shadows = np.flatnonzero(chosen)
    middle = (np.searchsorted(which, shadows) + np.searchsorted(which, shadows, side="right") - 1) // 2
    medians = np.zeros(len(chosen))
    medians[shadows] = value[middle]
    return medians


# Behind steel the detector sees the scatter, the light of the surroundings blurred: beside
# the air by the leg it is high, and a pin's excess over its background falls there. One
# pin's shadow was cut in two where its excess dipped below half its peak (scatter seeds 1,
# 10, 11, 25: 0.36-0.45 in the gap against 0.5-0.8 along the rest), the shorter piece was
# left out and the pin taken to end at the cut. Two pin-like shadows in line are one when
# the gap between them is short and still a bar over its sides all along: pins end to end
# leave tissue between them, as bright as beside them.
_JOIN_MAX_ANGLE_DEG = 2.0
_JOIN_MAX_OFFSET_WIDTHS = 0.25  # of the wider shadow: how far the shorter's axis may lie off the longer's
_JOIN_MAX_GAP_WIDTHS = 3.0  # of the narrower shadow: the longest gap joined
_JOIN_CONTRAST_SHARE = 0.5  # of the fainter shadow's typical excess: the gap's least over its sides
_JOIN_SIDE_PX = (3.0, 9.0)  # the gap's sides are read this far beyond its edges


def _gap_band(excess: np.ndarray, start: np.ndarray, stop: np.ndarray, width: float, beside: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along the gap from ``start`` to ``stop`` (a bar ``width`` wide), in slices of half a
    pixel: the median excess inside the bar, and the higher median of its two sides (from
    ``beside`` px off its line, clear of a wider shadow at either end); and the pixels (N,
    2: row, column) of the bar."""
    length = float(np.linalg.norm(stop - start))
    e = (stop - start) / max(length, 1e-9)
    m = np.array([-e[1], e[0]])
    s = np.arange(0.0, length + 0.5, 0.5)
    h, w = excess.shape

    def sample(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = start + s[:, None, None] * e + t[None, :, None] * m
        at = np.clip(np.round(p).astype(int), 0, [w - 1, h - 1])
        return excess[at[..., 1], at[..., 0]], at[..., ::-1]

    half = 0.5 * width - _JOIN_SIDE_PX[0]
    middle = np.median(sample(np.arange(-half, half + 1e-9, 1.0))[0], axis=1)
    outer = np.arange(beside, beside + _JOIN_SIDE_PX[1] - _JOIN_SIDE_PX[0] + 1e-9, 1.0)
    sides = np.maximum(np.median(sample(outer)[0], axis=1), np.median(sample(-outer)[0], axis=1))
    band = 0.5 * width + _JOIN_SIDE_PX[0]
    return middle, sides, sample(np.arange(-band, band + 1e-9, 0.5))[1].reshape(-1, 2)


def _join_in_line(labels: np.ndarray, good: np.ndarray, excess: np.ndarray, typical: np.ndarray
                  ) -> bool:
    """Join, in place, pin-like shadows that continue each other along one line across a
    short gap where the steel's excess dipped (``labels`` relabelled, ``good`` updated);
    returns whether any were joined."""
    joined, refused = False, set()
    bars = {label: _bar_and_width(pixels) for label, pixels in _pixels_of(labels, good).items()}
    while True:
        chosen = [int(label) for label in np.flatnonzero(good)]
        pair = next(((a, b) for i, a in enumerate(chosen) for b in chosen[i + 1:]
                     if (a, b) not in refused and _in_line(*bars[a], *bars[b])), None)
        if pair is None:
            return joined
        a, b = pair
        (bar_a, width_a), (bar_b, width_b) = bars[a], bars[b]
        toward = np.sign((bar_b.centre - bar_a.centre) @ bar_a.direction) * bar_a.direction
        start = bar_a.centre + bar_a.half_length * toward
        stop = bar_b.centre - bar_b.half_length * np.sign(toward @ bar_b.direction) * bar_b.direction
        beside = 0.5 * max(width_a, width_b) + _off_axis(bar_a, bar_b) + _JOIN_SIDE_PX[0]
        middle, sides, band = _gap_band(excess, start, stop, min(width_a, width_b), beside)
        if np.min(middle - sides) < _JOIN_CONTRAST_SHARE * min(typical[a], typical[b]):
            refused.add(pair)  # tissue between them: two shadows
            continue
        steel = band[(labels[band[:, 0], band[:, 1]] == 0)
                     & (excess[band[:, 0], band[:, 1]] > 0.5 * float(np.median(middle)))]
        labels[steel[:, 0], steel[:, 1]] = a
        labels[labels == b] = a
        good[b] = False
        ys, xs = np.nonzero(labels == a)
        bars[a] = _bar_and_width(np.column_stack([xs, ys]).astype(float))
        joined = True


def _bar_and_width(pixels: np.ndarray) -> tuple[_Bar, float]:
    """A shadow's fitted bar and its robust width: what the join compares, kept per label so
    that only a joined shadow is fitted again."""
    bar = _fit_bar(pixels)
    return bar, _robust_width(bar, pixels)


def _off_axis(a: _Bar, b: _Bar) -> float:
    """How far (px) the shorter bar's centre lies off the longer's axis."""
    longer, shorter = (a, b) if a.half_length >= b.half_length else (b, a)
    return abs(float((shorter.centre - longer.centre) @ longer.across))


def _in_line(a: _Bar, width_a: float, b: _Bar, width_b: float) -> bool:
    """Whether two bars lie on one line, parallel, with a short gap between their ends."""
    if np.degrees(np.arccos(min(abs(float(a.direction @ b.direction)), 1.0))) > _JOIN_MAX_ANGLE_DEG:
        return False
    longer, shorter = (a, b) if a.half_length >= b.half_length else (b, a)
    gap = abs(float((shorter.centre - longer.centre) @ longer.direction)) - longer.half_length - shorter.half_length
    return (_off_axis(a, b) <= _JOIN_MAX_OFFSET_WIDTHS * max(width_a, width_b)
            and 0.0 < gap <= _JOIN_MAX_GAP_WIDTHS * min(width_a, width_b))


def _clipped(A: np.ndarray, valid: np.ndarray, config: ContourConfig) -> np.ndarray:
    """Pixels at the frame's most attenuating level, above the field's typical level (a
    window clipped them), where at least a pin's least area is: a noisy frame that is not
    clipped reaches its top in a few pixels only."""
    inside = A[valid]
    if inside.size == 0:
        return np.zeros_like(valid)
    clipped = valid & (A >= inside.max())
    if np.count_nonzero(clipped) < config.pin_min_area_px:
        return np.zeros_like(valid)
    return clipped


def _pins(A: np.ndarray, valid: np.ndarray, broad: np.ndarray, shutters: np.ndarray, config: ContourConfig,
          expected: np.ndarray | None, expected_width_px: float | None,
          expected_length_px: float | None) -> tuple[list[np.ndarray], np.ndarray, dict]:
    """Edge points of pin 1 and pin 2, the pins' shadow mask, and diagnostics."""
    widths = _PinWidths.of(config, expected_width_px)
    background = _below_pins(A, broad, config)
    excess = np.where(valid, A - background, 0.0).astype(np.float32)
    # Scatter adds to what passes steel and bone alike, so steel's excess over its
    # surroundings shrinks (to ~0.6 at a scatter-to-primary of 1): a shadow is grown from
    # its seeds down to half of its own peak excess where that is below _PIN_GROW_TO.
    # A C-arm's window may clip steel at the frame's most attenuating level: the pins are
    # then flat at that level, and their excess is only how far the bone or tissue under
    # each lies below it (processing seed 10: 0.52 and 0.34). What the frame shows as
    # opaque as it can show anything seeds a shadow too; its shape decides.
    clipped = _clipped(A, valid, config)
    strong = (excess > config.pin_threshold) | clipped
    count, components = cv2.connectedComponents(strong.astype(np.uint8), connectivity=8)
    seeds = np.asarray(components, np.int32)
    peak = np.zeros(count, np.float32)
    np.maximum.at(peak, seeds[strong], excess[strong])
    reach = cv2.dilate(peak[seeds] * strong, np.ones((31, 31), np.uint8))
    weak = ((excess > np.minimum(0.5 * reach, _PIN_GROW_TO)) & (reach > 0)) | clipped
    count, labels, stats, _ = cv2.connectedComponentsWithStats(weak.astype(np.uint8), connectivity=8)
    good, stub_pixels = _pin_like(labels, count, widths, config)
    # Shadows shaped like a pin seen end-on, traced only if two of them (or one and a bar)
    # converge as the pins (below); taken before _split_crossed cuts pieces out of them.
    under = _under_shutters(labels, count, shutters)
    stubs = [pixels for label, pixels in stub_pixels.items() if not under[label]]
    count, good = _split_crossed(labels, stats, good, widths, config)
    good &= ~_under_shutters(labels, count, shutters)
    level: float | None = None
    # Steel is the most attenuating: bars of bone (a cortex seen tangentially) are far fainter.
    # Each bar's typical excess, not its peak: a C-arm's window clips the darkest pixels,
    # and where it clips part of one pin the other's peak is a third of it (processing
    # seed 28: 8.7 against 3.4, medians 3.0 and 2.5).
    if good.any():
        typical = _medians(excess, labels, good)
        if _join_in_line(labels, good, excess, typical):
            typical = _medians(excess, labels, good)
        level = _steel_level(typical[good])
        good &= typical >= _PIN_PEAK_SHARE * level
    stubs = _steel_stubs(stubs, excess, level)
    mask = cv2.morphologyEx(good[labels].astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    count = _split_notched(labels, mask, count, good, widths, config)
    # Steel is so opaque that log-attenuation bends its blurred edge inwards: the edge is
    # placed on the transmitted intensity instead, where it is a blurred step.
    transmission = cv2.GaussianBlur(np.exp(-(A - background)).astype(np.float32), (0, 0),
                                    config.smoothing_px)
    grad = gradient(-transmission)
    edges, normals = _outline_edges(mask, grad, config)
    if len(edges) < _MIN_PIN_EDGES and len(stubs) < 2:
        empty = np.zeros((0, 2))
        return [empty, empty], mask, {"pins_found": 0}
    ys, xs = np.nonzero(mask)
    kept = np.bincount(labels[ys, xs], minlength=count)  # pixels of each shadow after the opening
    pixels = np.column_stack([xs, ys]).astype(float)
    shadows = np.argsort(kept)[::-1][:min(np.count_nonzero(kept), _PIN_CANDIDATES)]
    fitted = [(_fit_bar(pixels[labels[ys, xs] == t]), pixels[labels[ys, xs] == t]) for t in shadows]
    least_length = 0.0 if expected_length_px is None else _PIN_LENGTH_SHARE * expected_length_px
    pair = _parallel_pair(fitted, widths, expected, least_length)
    split = None if pair is not None else _split_one(labels, shadows, edges, normals, widths,
                                                      least_length, config)
    if not isinstance(split, tuple) and least_length > 0:
        # The initial pose may foresee a far longer shadow than a pin seen nearly along its
        # axis casts (at level 3, 434-589 px for 133-216: idealised seeds 0, 2, 12, 23, 28):
        # two separate parallel bars of a pin's width are then the pins whatever their
        # length. A single shadow is still not cut into two short halves (see _split_one).
        pair = _parallel_pair(fitted, widths, expected)
        if pair is None:
            # Likewise one shadow whose sides step where one pin ends and the other begins
            # holds two pins whatever their length: steps are evidence, unlike a split in
            # the middle of a bar with none (the real tibia's seed 11 at level 3, view 1:
            # pins in line, 139 and 153 px long, foreseen 381).
            stepped = _split_one(labels, shadows, edges, normals, widths, _PIN_ELONGATION * widths.least,
                                 config, stepped_only=True)
            split = stepped if isinstance(stepped, tuple) else split
    if pair is None and not (isinstance(split, tuple) and split[1] != "coincident"):
        # Then the pins seen nearly end-on, before a split that nothing located (a blade
        # halved: operating-room seed 8, view 1) but after one that steps or heads locate:
        # two blades' pieces may point at one point too (operating-room seed 16, view 2,
        # taken over the pins in line).
        candidates = fitted + [(_fit_bar(pixels), pixels) for pixels in stubs]
        pair = _parallel_pair(candidates, widths, expected, converging=True)
        if pair is not None and max(pair) >= len(fitted):  # a stub is one of them: trace it
            for i in pair:
                mask[candidates[i][1][:, 1].astype(int), candidates[i][1][:, 0].astype(int)] = True
            edges, normals = _outline_edges(mask, grad, config)
        fitted = candidates
    if pair is not None:
        bars, overlap = [fitted[i][0] for i in pair], "apart"
    elif isinstance(split, tuple):
        bars, overlap, edges = split
    else:
        empty = np.zeros((0, 2))
        return [empty, empty], mask, {"pins_found": 0, "pins_one_bar": split}
    bars = _order_pins(bars, config, expected)
    distance = np.stack([np.abs(b.distance(edges)) for b in bars])
    if overlap == "apart":
        # The outline of every steel-like shadow was traced: only the pair's own edges
        # are the pins' (a processed plateau's dark band beside a pin is not).
        own = np.min(distance, axis=0) <= _PIN_EDGE_REACH_PX
        edges, distance = edges[own], distance[:, own]
    # Where the two pins' edges are closer than a step can be seen, a point is on both.
    shared = 0.5 * config.pin_min_step_px
    result = [_without_head(edges[distance[i] <= distance[1 - i] + shared], bars[i]) for i in range(2)]
    info = {"pins_found": 2 if all(len(r) for r in result) else sum(bool(len(r)) for r in result),
            "pins_overlap": overlap,
            "pin_centres_px": [b.centre.tolist() for b in bars],
            "pin_widths_px": [2 * b.half_width for b in bars]}
    return result, mask, info


# -- bone ----------------------------------------------------------------------------------

def _poly_terms(u: np.ndarray, v: np.ndarray, degree: int) -> np.ndarray:
    return np.column_stack([u**i * v**j for i in range(degree + 1) for j in range(degree + 1 - i)])


def _tissue_surface(A: np.ndarray, tissue: np.ndarray, config: ContourConfig) -> np.ndarray:
    """Least-squares low-order surface through the soft tissue's attenuation (downsampled)."""
    f = config.background_downscale
    h, w = A.shape
    small = cv2.resize(A, (w // f, h // f), interpolation=cv2.INTER_AREA)
    known = cv2.resize(tissue.astype(np.uint8), (w // f, h // f), interpolation=cv2.INTER_NEAREST) > 0
    vs, us = np.nonzero(known)
    scale = max(small.shape)
    coef = np.linalg.lstsq(_poly_terms(us / scale - 0.5, vs / scale - 0.5, config.background_degree),
                           small[vs, us], rcond=None)[0]
    gv, gu = np.mgrid[0:small.shape[0], 0:small.shape[1]]
    surface = (_poly_terms(gu.ravel() / scale - 0.5, gv.ravel() / scale - 0.5, config.background_degree)
               @ coef).reshape(small.shape).astype(np.float32)
    return cv2.resize(surface, (w, h), interpolation=cv2.INTER_LINEAR)


def _distance_to(mask: np.ndarray) -> np.ndarray:
    """Distance (px) of every pixel to a mask, infinite without one; thresholds of it are
    round dilations, several from one transform."""
    if not mask.any():
        return np.full(mask.shape, np.inf, np.float32)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)


def _not_tissue(smooth: np.ndarray, valid: np.ndarray, air: np.ndarray, skin: np.ndarray,
                grad, config: ContourConfig) -> np.ndarray:
    """Where the field is neither air nor soft tissue: bone (and the pins, which are sought
    apart and meanwhile).

    Soft tissue has no strong edges except at the skin: the tissue region is what can be
    reached from the skin without crossing one. Regions cut off from the skin by bone (the
    gap between tibia and fibula) are tissue too when their attenuation is that of the
    tissue around them, unlike the marrow inside a bone, which carries the bone's walls.
    """
    magnitude = np.hypot(grad[0], grad[1])
    # A C-arm's edge enhancement gives soft tissue gradients of its own (halos, sharpened
    # skin lines): where half the field changes faster than the barrier, the tissue is cut
    # into pieces and the bone mask leaks into them. The barrier then rises to twice the
    # field's median gradient (bone edges are stronger still).
    barrier_strength = max(config.barrier_strength,
                           _TISSUE_GRADIENT_FACTOR * float(np.median(magnitude[valid][::7])))
    barrier = cv2.dilate((magnitude > barrier_strength).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    open_area = (valid & ~barrier & ~air).astype(np.uint8)
    count, labels = cv2.connectedComponents(open_area, connectivity=4)
    seeded = np.bincount(labels[skin & (open_area > 0)], minlength=count) > 0
    seeded[0] = False
    tissue = seeded[labels]
    if not tissue.any():
        raise ContourError("no soft tissue next to the skin is visible; cannot separate the bone")
    excess = smooth - _tissue_surface(smooth, tissue & ~skin if (tissue & ~skin).any() else tissue, config)
    flat = labels.ravel().astype(np.intp)  # as np.bincount takes them: converted once, not thrice
    sizes = np.bincount(flat, minlength=count)
    level = np.bincount(flat, weights=excess.ravel(), minlength=count) / np.maximum(sizes, 1)
    # A region cut off from the skin is tissue when its level over that surface is tissue's.
    enclosed_tissue = ~seeded & (sizes >= config.min_bone_area_px // 10) & (level < config.bone_threshold)
    enclosed_tissue[0] = False
    # Or, where that surface is extrapolated too far to say: when it is wide (the gap between
    # tibia and fibula, whose edges the model's outer outline does not follow, is left to the
    # level), no higher than the tissue by the skin (a tibia's interior is) and below every
    # bone around it. The last, costliest test only where the others leave a region.
    raw_level = np.bincount(flat, weights=smooth.ravel(), minlength=count) / np.maximum(sizes, 1)
    skin_tissue = smooth[tissue][::7]
    tissue_top = min(float(np.percentile(skin_tissue, _TISSUE_TOP_PERCENTILE)),
                     float(np.median(skin_tissue)) + _CUT_OFF_EXCESS * config.bone_threshold)
    cut_off = ~seeded & ~enclosed_tissue & (sizes >= _CUT_OFF_AREA * config.min_bone_area_px) & (
        raw_level <= tissue_top)
    cut_off[0] = False
    if cut_off.any():
        cut_off &= _share_below_surroundings(labels, count, barrier, smooth, grad,
                                             config.bone_threshold) >= _LOWER_SHARE
        enclosed_tissue |= cut_off
    tissue |= enclosed_tissue[labels]
    return valid & ~air & ~tissue


def _bone(not_tissue: np.ndarray, valid: np.ndarray, pins: np.ndarray, grad,
          config: ContourConfig) -> tuple[np.ndarray, dict]:
    """Sub-pixel outer edges of tibia with fibula (the outline of what is neither air nor
    tissue, with the pins' shadows over it), and diagnostics."""
    bone = (not_tissue | pins) & valid
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    bone = cv2.morphologyEx(bone.astype(np.uint8), cv2.MORPH_OPEN, kernel)
    count, labels, areas = components(bone, 8)
    big = np.zeros(count, bool)
    big[1:] = areas[1:] >= config.min_bone_area_px
    bone = big[labels]
    # Holes smaller than the minimum bone area are noise inside bone, not gaps between bones.
    bone = fill_holes(bone, config.min_bone_area_px)
    points, normals = outline_with_normals(bone, 30)
    edges, strength, sigma = bone_edges(grad, points, normals, config.edge_search_px,
                                        config.edge_search_px + config.bone_reach_in_px,
                                        config.min_edge_strength, config.bone_edge_offset_px)
    return edges, {"bone_mask_area_px": int(bone.sum()), "bone_candidates": len(points),
                   "edge_blur_sigma_px": sigma,
                   "bone_edge_strength_median": float(np.median(strength)) if len(strength) else 0.0}


def _share_below_surroundings(labels: np.ndarray, count: int, barrier: np.ndarray, smooth: np.ndarray,
                              grad: tuple[np.ndarray, np.ndarray], step: float) -> np.ndarray:
    """Per component, the share of the edges around it (weighted by their strength) across
    which the attenuation rises away from it by at least ``step``.

    Soft tissue cut off from the skin by bones (beside the fibula when a femur closes the
    joint space above it and no air shows beyond) lies below everything around it, as the
    gap between tibia and fibula does; a bone region rises above its surroundings at its
    outline. Its level against the tissue surface cannot tell them apart there: that surface
    is fitted to the tissue by the skin, and across a wide leg the tissue thickens by more
    than a bone adds."""
    gx, gy = grad
    v, u = np.nonzero(barrier)
    magnitude = np.hypot(gx[v, u], gy[v, u])
    ok = magnitude > 0
    v, u, magnitude = v[ok], u[ok], magnitude[ok]
    du, dv = gx[v, u] / magnitude, gy[v, u] / magnitude
    h, w = labels.shape

    def side(sign: float) -> tuple[np.ndarray, np.ndarray]:
        """The first region met walking from each edge pixel along (or against) the
        gradient, and the attenuation where it was met."""
        found, level = np.zeros(len(v), labels.dtype), np.zeros(len(v), np.float32)
        for reach in _EDGE_SIDE_PX:
            rows = np.clip(np.rint(v + sign * reach * dv).astype(int), 0, h - 1)
            cols = np.clip(np.rint(u + sign * reach * du).astype(int), 0, w - 1)
            new = found == 0
            found = np.where(new, labels[rows, cols], found)
            level = np.where(new, smooth[rows, cols], level)
        return found, level

    (lower, low), (upper, high) = side(-1.0), side(1.0)
    # Only edges with a region on both sides say which is the lower (a narrow region's far
    # side would otherwise go uncounted), and only steps as large as a bone makes (weaker
    # ones are noise or texture within a bone).
    both = (lower > 0) & (upper > 0) & (lower != upper) & (high - low >= step)
    below = np.bincount(lower[both], weights=magnitude[both], minlength=count)
    above = np.bincount(upper[both], weights=magnitude[both], minlength=count)
    return below / np.maximum(below + above, 1e-12)


_EDGE_SIDE_PX = (2.0, 4.0, 6.0, 9.0)  # steps from an edge pixel, along the gradient, to the regions it parts
_LOWER_SHARE = 0.8  # of its edges' strength: a region this much below its surroundings is tissue
_CUT_OFF_AREA = 10  # bone areas: cut-off tissue this large is not a gap between bones
# The highest level cut-off tissue may have: the skin's tissue's 95th percentile, and at most
# this many bone thresholds over its median (where the skin's "tissue" holds a collimator
# blade's penumbra, its upper percentiles are the blade's); a tibia's interior, below its
# cortex, lies 3.5-8 thresholds over the median, cut-off tissue up to 2.8 (measured).
_TISSUE_TOP_PERCENTILE = 95.0
_CUT_OFF_EXCESS = 3.0


def _smoothing_for_noise(A: np.ndarray, valid: np.ndarray, config: ContourConfig) -> float:
    """The Gaussian sigma (px) that keeps the noise of the attenuation's gradient well under
    the soft tissue's barrier: ``config.smoothing_px`` at full dose, more at low dose (a
    tenth of the quanta, ~3x the noise per pixel). The noise is read from differences of
    neighbouring pixels (robust: edges are few)."""
    diff = (A[1:, :] - A[:-1, :])[::2, ::2][(valid[1:, :] & valid[:-1, :])[::2, ::2]]
    if diff.size < 100:
        return config.smoothing_px
    noise = 1.4826 * float(np.median(np.abs(diff - np.median(diff)))) / np.sqrt(2.0)
    # The derivative of a Gaussian of sigma s passes white noise of SD n as ~n / (2.5 s^2).
    needed = np.sqrt(noise / (2.5 * _GRADIENT_NOISE_SHARE * config.barrier_strength))
    return float(np.clip(needed, config.smoothing_px, _MAX_SMOOTHING_PX))


_TISSUE_GRADIENT_FACTOR = 2.0
_GRADIENT_NOISE_SHARE = 0.25  # of the barrier strength: the gradient noise's SD at most
_MAX_SMOOTHING_PX = 4.0


# How far inside an intensifier's rim a processed frame is left out: unsharp masking of
# 6-30 px leaves the rim's halo there (coverage of the true outline on 18 simulated
# processed frames: 55% with none, 62% with 40 px; bone median within 3 px: 8 -> 10 frames).
_PROCESSED_RIM_HALO_PX = 40.0
_HIDDEN_NEAR_PX = 60.0  # an expected pin centre this close to opaque metal: hidden by it


def _why_missing(index: int, expected: np.ndarray | None, broad: np.ndarray, one_bar: str | None) -> str:
    """Why pin ``index`` (0, 1) has no edges in a frame, in words for the refusal."""
    if one_bar == ONE_BAR_TWO_WIDE:
        return ("not told from the other pin (one bar as wide as both: the pins lie one "
                "behind the other)")
    if one_bar == ONE_BAR_ONE_WIDE:
        return ("not told from the other pin (one bar a pin wide: the pins lie in line, one "
                "behind the other, or the other is hidden)")
    if broad.any():
        if expected is None:
            return "not found (hidden by metal?)"
        centre = np.asarray(expected, float).reshape(2, 2)[index]
        ys, xs = np.nonzero(broad[::4, ::4])
        if len(xs) and float(np.min(np.hypot(4 * xs - centre[0], 4 * ys - centre[1]))) <= _HIDDEN_NEAR_PX:
            return "hidden by metal"
    return "not found (no steel bar of a pin's shape)"


def _broad_opaque(A: np.ndarray, valid: np.ndarray, config: ContourConfig) -> np.ndarray:
    """Regions far more attenuating than the field and wider than any pin: collimator
    blades, retractor blades, a femur seen end-on. No edge in or beside them is the tibia's
    (what they hide is left out, not guessed), and no steel in them is a pin."""
    sub = A[::2, ::2][valid[::2, ::2]]
    if sub.size == 0:
        return np.zeros_like(valid)
    opaque = (valid & (A > float(np.median(sub)) + config.opaque_excess)).astype(np.uint8)
    # Opened by a disk wider than any pin, through two distance transforms: eroded where
    # the nearest clear pixel is further than its radius, then grown back by it. The same
    # mask as cv2.morphologyEx with a 91 px ellipse but for a few rim pixels, in a fifth
    # of its time (it was a third of an extraction).
    # Both transforms are exact, so each is taken only over the box that can matter: the
    # opaque pixels' with a clear rim, then the eroded pixels' grown by the radius.
    radius = int(config.pin_width_px[1])
    inner = np.zeros_like(valid)
    box = _box(opaque, 1)
    if box is None:
        return inner
    inner[box] = cv2.distanceTransform(opaque[box], cv2.DIST_L2, cv2.DIST_MASK_PRECISE) > radius
    broad = np.zeros(valid.shape, np.uint8)
    box = _box(inner, radius + 1)
    if box is None:
        return inner
    grown = cv2.distanceTransform((~inner[box]).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    broad[box] = grown <= radius
    return cv2.dilate(broad, np.ones((5, 5), np.uint8)) > 0


def _box(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """The bounding box of a mask grown by ``margin`` px (within the frame), None if empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    h, w = mask.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)))


def _border(broad: np.ndarray) -> np.ndarray:
    """The rim of broad metal. A pin's edges over a face-on blade are placed as over
    tissue (2 mm of steel passes quanta, and the pin's background there is the blade): a
    pin across blades kept a third of its edges (retractors seeds 1, 10, 22: pins 5-6 deg
    from parallel). Only at the rim, where the background steps, are they left out."""
    return broad & ~(cv2.erode(broad.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)


# An unforeseen failure inside a step is still a frame we cannot read, not a crash of the
# caller: it is refused naming the step (the fuzz test over varied frames keeps it unused).
_UNFORESEEN = (ValueError, TypeError, IndexError, ZeroDivisionError, FloatingPointError,
               np.linalg.LinAlgError, cv2.error)
UNFORESEEN_PREFIX = "contour extraction failed unexpectedly"


def extract_contours(pixels: np.ndarray, config: ContourConfig = ContourConfig(),
                     expected_pins: np.ndarray | None = None,
                     expected_pin_width_px: float | None = None,
                     expected_pin_length_px: float | None = None) -> ExtractedContours:
    """Bone and pin edge pixels of one frame, in raw (distorted) pixel coordinates.

    ``expected_pins``: optional (2, 2) projected centres of pin 1 and pin 2 (e.g. from the
    initial pose) that decide the labels instead of ``config.pin_order`` where they are
    clear, and favour the pin pair near them. ``expected_pin_width_px``: optional width of
    a pin's shadow there (the plan's pin diameter projected), which tells pins from other
    straight metal of another width. Whatever the frame, the only error raised is
    :class:`ContourError`, with the reason.
    """
    if expected_pin_width_px is not None and not expected_pin_width_px > 0:
        raise ValueError(f"expected_pin_width_px must be positive, got {expected_pin_width_px}")
    try:
        scale = _working_scale(pixels)
        if scale == 1.0:
            return _extract(pixels, config, expected_pins, expected_pin_width_px, expected_pin_length_px)
        found = _extract(_reduced(np.asarray(pixels), scale), config,
                         None if expected_pins is None else to_working_pixels(np.asarray(expected_pins, float), scale),
                         None if expected_pin_width_px is None else expected_pin_width_px / scale,
                         None if expected_pin_length_px is None else expected_pin_length_px / scale)
        return _on_frame_pixels(found, scale)
    except ContourError:
        raise
    except FieldError as exc:
        raise ContourError(str(exc)) from None
    except _UNFORESEEN as exc:
        raise ContourError(f"{UNFORESEEN_PREFIX} ({type(exc).__name__}: {exc})") from exc


# The extraction's lengths in pixels (smoothing, edge search reach, the pins' least area,
# the reach of metal and shutters) are made for frames of about a thousand pixels a side (a
# 23 cm field at 0.2-0.3 mm a pixel). A flat panel's larger frame is reduced to about that
# first, by a quarter-step factor (so that a cell of the bone region, VISIBLE_CELL_PX
# reduced pixels, is a whole number of the frame's): extracted directly, idealised frames
# of 2048 px were refused in 7 of 14 cases and 1536 px ones measured 0.3-0.8 deg off where
# 1024 px frames are within 0.1 deg (docs/realism.md, twentieth pass).
WORKING_SIDE_PX = 1024
_SCALE_STEPS = 4  # a working scale is a whole number of quarters


def _working_scale(pixels: np.ndarray) -> float:
    """How many times to reduce a frame a side (1: extracted as it is): the quarter step
    that brings its shorter side nearest :data:`WORKING_SIDE_PX`, for 2-D frames of numbers
    (1 up to a shorter side of 1152 px, 9/8 of it)."""
    image = np.asarray(pixels)
    if image.ndim != 2 or image.dtype.kind not in "uif":
        return 1.0  # not a frame: _extract says why
    return max(1.0, round(_SCALE_STEPS * min(image.shape) / WORKING_SIDE_PX) / _SCALE_STEPS)


def _reduced(image: np.ndarray, scale: float) -> np.ndarray:
    """The frame reduced ``scale`` times a side, each pixel the mean of the frame's it
    covers, in the frame's own type (integer grey levels rounded); the last rows and
    columns that make no whole block of ``scale`` steps are left out."""
    block = int(round(scale * _SCALE_STEPS))  # frame pixels to _SCALE_STEPS reduced ones
    h, w = (side - side % block for side in image.shape)
    if scale == int(scale):
        f = int(scale)
        mean = image[:h, :w].astype(np.float64).reshape(h // f, f, w // f, f).mean(axis=(1, 3))
    else:
        mean = cv2.resize(image[:h, :w].astype(np.float64), (round(w / scale), round(h / scale)),
                          interpolation=cv2.INTER_AREA)
    return mean if image.dtype.kind == "f" else np.rint(mean).astype(image.dtype)


def _on_frame_pixels(found: ExtractedContours, scale: float) -> ExtractedContours:
    """Contours extracted from a frame reduced ``scale`` times a side, on the frame itself
    (the diagnostics' lengths stay in the reduced frame's pixels, which they say)."""
    edge_search = None if found.bone_edge_search is None else replace(found.bone_edge_search, scale=scale)
    bone, pin1, pin2 = (to_frame_pixels(points, scale) for points in (found.bone, found.pin1, found.pin2))
    return ExtractedContours(bone, pin1, pin2, found.diagnostics | {"working_scale": scale}, found.bone_visible,
                             edge_search, int(round(found.visible_cell_px * scale)))


def agreed_polarity(extracted: Sequence[ExtractedContours | None]) -> str | None:
    """The polarity ("dark", "bright") to extract again with the frames of one case that
    read another or could not be extracted (None), or None when they agree or nothing clear
    says otherwise.

    A case's frames come from one C-arm that stores them alike. Where the frames whose own
    content says their polarity clearly (``polarity_decisive``) agree, a frame read
    otherwise from weaker cues is read wrongly: shutters seeds 14 and 23 had view 1's taken
    inverted, a collimator blade's bright edge passing for steel, and their bone stage went
    astray (view 2's periphery says "dark" four to ten times over the decisive level). A
    frame whose own polarity could not be told at all is read as they read too (the real
    tibia's operating-room seed 18, view 1: "no steel stands out", and the case was refused
    before the solve), and, where none read it clearly, as the others agree it reads: a
    weak reading beats none (seed 1 of the operating room at the standard views: a
    processed flat-panel frame, its pins off the centre, whose partner read "dark" weakly;
    read so it measures). Read wrongly, a frame's bone stage goes astray and the case is
    refused as it would have been."""
    read = [f.diagnostics for f in extracted if f is not None]
    clear = {d.get("polarity") for d in read if d.get("polarity_decisive")}
    unread = any(f is None for f in extracted)
    if not clear and unread:
        clear = {d.get("polarity") for d in read}
    if len(clear) != 1:
        return None
    polarity = clear.pop()
    return polarity if unread or any(d.get("polarity") != polarity for d in read) else None


def _extract(pixels: np.ndarray, config: ContourConfig, expected_pins: np.ndarray | None,
             expected_pin_width_px: float | None, expected_pin_length_px: float | None
             ) -> ExtractedContours:
    start = time.perf_counter()
    image = np.asarray(pixels)
    if image.ndim != 2 or min(image.shape) < 64:
        raise ContourError(f"expected a 2-D grey-scale frame of at least 64 x 64, got {image.shape}")
    if image.dtype.kind not in "uif" or image.dtype.kind == "c":
        raise ContourError(f"expected grey levels as numbers, got {image.dtype}")
    if image.dtype.kind == "f" and np.all(np.isfinite(image)) and np.ptp(image) > 0:
        # Floating-point grey levels (any scale, half precision too) onto a 16-bit range in
        # double precision: attenuation counts in quanta.
        image = image.astype(np.float64)
        image = (image - image.min()) * (65535.0 / np.ptp(image))
    h, w = image.shape
    image, overlay = remove_overlays(image)
    centre, radius, outside, sign, sign_decisive = field_of_view(image, config.polarity)
    u, v = np.arange(w)[None, :], np.arange(h)[:, None]
    r = np.hypot(u - centre[0], v - centre[1])
    valid = r < (radius if radius is not None else np.inf) - 2.0
    if radius is None:
        valid &= (u >= 2) & (v >= 2) & (u < w - 2) & (v < h - 2)
    valid &= ~cv2.dilate(overlay.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    if valid.sum() < config.min_bone_area_px:
        raise ContourError("the field of view is too small to hold a tibia")
    # A frame stored through a log or gamma response is not linear in the quanta: its
    # attenuation is read from its own noise (or spread) instead of -log of the grey level.
    A, response = frame_attenuation(image, valid, outside, sign)
    # The C-arm that processed the frame also sharpened it: the field's rim, a step up from
    # no signal, leaves a halo inside the circle that is neither air nor tissue.
    halo = _PROCESSED_RIM_HALO_PX if response != "linear" and radius is not None else 0.0
    valid &= r < (radius if radius is not None else np.inf) - halo
    broad = _broad_opaque(A, valid, config)
    field = valid.copy()
    # A collimator blade too faint to be opaque (scatter, processing) hides the bone as
    # well: its noise and its straight edge are no bone's (pins are still sought there).
    shutters, shutter_lines = collimator_shutters(A, valid & ~broad)
    valid &= ~broad & ~shutters
    # Levels of the field from every other row and column: as good, and a quarter of the sort.
    fill = float(np.median(A[::2, ::2][valid[::2, ::2]]))
    # A pin is sought over broad metal too (a blade is no pin but a pin may cross it).
    A_field = np.where(field, A, fill).astype(np.float32)
    A = np.where(valid, A, fill).astype(np.float32)
    # The pins are sought on the second core while the bone's tissue is told apart here:
    # both are mostly OpenCV and numpy, which release the GIL.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="pins") as pool:
        found_pins = pool.submit(_pins, A_field, field, broad & field, shutters, config, expected_pins,
                                 expected_pin_width_px, expected_pin_length_px)
        smoothing = _smoothing_for_noise(A, valid, config)
        smooth = cv2.GaussianBlur(A, (0, 0), smoothing)
        grad = gradient(smooth)
        coarse = cv2.GaussianBlur(A, (0, 0), 3.0)
        air = valid & (coarse < np.percentile(coarse[::2, ::2][valid[::2, ::2]], 0.5) + config.air_margin)
        to_air = _distance_to(air)
        not_tissue = _not_tissue(smooth, valid, air, to_air <= config.skin_margin_px, grad, config)
        margin = config.fov_margin_px
        rim_ok = r < (radius if radius is not None else np.inf) - margin - halo
        if radius is None:
            rim_ok &= (u >= margin) & (v >= margin) & (u < w - margin) & (v < h - margin)
        pins_ok = rim_ok & (_distance_to(_border(broad)) > margin)
        rim_ok &= _distance_to(broad | shutters) > margin
        (pin1, pin2), pins, pin_info = found_pins.result()
    bone, bone_info = _bone(not_tissue, valid, pins, grad, config)
    # Where the frame shows a bone's edge: in the exposed field, clear of metal, text and
    # the pins' shadows (air shows it too: a bone there would stand out).
    bone_visible = valid & rim_ok & (_distance_to(pins) > config.pin_exclusion_px)
    bone_edges_visible = bone_visible & (to_air > 3.0)
    bone = kept_in(bone, bone_edges_visible)
    pin1, pin2 = kept_in(pin1, pins_ok), kept_in(pin2, pins_ok)
    missing = {label: _why_missing(k, expected_pins, broad, pin_info.get("pins_one_bar"))
               for k, (label, points) in enumerate((("pin1", pin1), ("pin2", pin2)))
               if len(points) < _MIN_PIN_EDGES}
    diagnostics = {
        "fov_centre_px": centre.tolist(), "fov_radius_px": radius,
        "polarity": "dark" if sign > 0 else "bright",
        "polarity_decisive": sign_decisive,
        "response": response, **pin_info, **bone_info,
        "opaque_area_px": int(broad.sum()), "shutters": len(shutter_lines),
        "smoothing_px": smoothing, "missing": missing,
        "points": {"bone": len(bone), "pin1": len(pin1), "pin2": len(pin2)},
        "seconds": time.perf_counter() - start,
    }
    half = VISIBLE_CELL_PX // 2
    return ExtractedContours(bone, pin1, pin2, diagnostics,
                             bone_visible[half::VISIBLE_CELL_PX, half::VISIBLE_CELL_PX].copy(),
                             BoneEdgeSearch.of_frame(smooth, bone_edges_visible, config.min_edge_strength,
                                                     config.bone_edge_offset_px))


def load_manual_contours(path: str | Path) -> tuple[str, dict[str, ExtractedContours]]:
    """Hand-drawn contours: ``(coordinates, {view_id: contours})``.

    Format ``slamtka-contours/1``: ``{"format", "units": "px", "coordinates": "raw" |
    "undistorted", "views": [{"view_id", "bone" (or "tibia"), "pin1", "pin2"}]}`` with points
    as ``[u, v]`` pairs. ``coordinates`` defaults to ``undistorted`` (the case-folder file);
    points drawn on the frames as received are ``raw`` and are undistorted with the
    calibration before solving.
    """
    path = Path(path)
    try:
        doc = read_json_object(path)
    except ValueError as exc:
        raise ContourError(str(exc)) from None
    if doc.get("format") != _CONTOURS_FORMAT:
        raise ContourError(f"{path}: format {doc.get('format')!r} is not {_CONTOURS_FORMAT!r}")
    if doc.get("units", "px") != "px":
        raise ContourError(f"{path}: units {doc.get('units')!r} are not px")
    coordinates = doc.get("coordinates", "undistorted")
    if coordinates not in ("raw", "undistorted"):
        raise ContourError(f"{path}: coordinates {coordinates!r} must be raw or undistorted")
    views: dict[str, ExtractedContours] = {}
    for i, entry in enumerate(doc.get("views") or []):
        view_id = str(entry.get("view_id") or "")
        if not view_id or view_id in views:
            raise ContourError(f"{path}: view {i} has a missing or repeated view_id")
        if ("bone" in entry) == ("tibia" in entry):
            raise ContourError(f"{path}: view {view_id} needs exactly one of 'bone' or 'tibia'")
        labelled = {}
        for label, key in (("bone", "bone" if "bone" in entry else "tibia"), ("pin1", "pin1"),
                           ("pin2", "pin2")):
            try:
                pts = np.asarray(entry.get(key, []), dtype=float).reshape(-1, 2)
            except ValueError:
                raise ContourError(f"{path}: view {view_id} {key} must be a list of [u, v]") from None
            if not np.all(np.isfinite(pts)):
                raise ContourError(f"{path}: view {view_id} {key} has non-finite points")
            labelled[label] = pts
        views[view_id] = ExtractedContours(labelled["bone"], labelled["pin1"], labelled["pin2"],
                                           diagnostics={"source": "manual"})
    if not views:
        raise ContourError(f"{path}: no views")
    return coordinates, views
