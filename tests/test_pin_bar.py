"""A pin's fitted bar: as wide as its shaft, whatever small thing touches its side."""

from __future__ import annotations

import cv2
import numpy as np

from slamtka.solver.imaging.contours import (
    ContourConfig,
    _Bar,
    _converging,
    _fit_bar,
    _parallel_pair,
    _PinWidths,
    _split_notched,
    _steel_level,
    _under_shutters,
)
from slamtka.solver.imaging.edges import outline_with_normals


def _pixels(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.column_stack([xs, ys]).astype(float)


def test_a_stroke_touching_a_pins_side_does_not_widen_its_bar():
    """Marker seed 15: a lead marker's thin stroke across pin 1's side made its bar 62 px
    wide for a 21 px shaft, and the shaft's edges, then 20 px inside the bar's sides, were
    left off the pin."""
    mask = np.zeros((200, 600), bool)
    mask[90:111, 150:450] = True  # the shaft, 21 px wide
    mask[50:90, 300:306] = True  # the stroke: 40 px off its side, 4% of the shadow
    bar = _fit_bar(_pixels(mask))
    assert 2.0 * bar.half_width < 23.0
    assert abs(bar.half_length - 150.0) < 3.0


def test_a_bars_outline_points_give_its_width():
    """Edge points all lie on the sides: their top percentile is the half-width."""
    mask = np.zeros((200, 600), bool)
    mask[90:111, 50:550] = True
    edges, _ = outline_with_normals(mask, 10)
    bar = _fit_bar(edges)
    assert abs(2.0 * bar.half_width - 21.0) < 2.0


def test_a_shadow_mostly_under_a_shutter_is_no_pin_candidate():
    """A band along a shutter's edge lies inside the shutter's mask; a pin that runs under a
    shutter with most of its length in the field is still a candidate."""
    labels = np.zeros((200, 600), np.int32)
    labels[10:190, 5:26] = 1  # a band along the left shutter's edge
    labels[90:111, 20:320] = 2  # a pin whose end runs under that shutter
    shutter = np.zeros(labels.shape, bool)
    shutter[:, :30] = True
    assert _under_shutters(labels, 3, shutter)[1:].tolist() == [True, False]


def test_two_bars_further_apart_than_a_blocks_pins_are_not_the_pair():
    """Operating-room seed 4, view 1 (AP): two blades seen edge-on either side of the
    plateau, parallel and a pin wide, 26 widths apart, were taken for the pins; a block's
    pins lie at most some 11 widths apart across. Pins in line stay a pair however far
    apart along their axis their centres lie."""
    widths = _PinWidths.of(ContourConfig(), 22.0)

    def bar_at(x: float, y: float, vertical: bool) -> tuple[_Bar, np.ndarray]:
        mask = np.zeros((900, 1400), bool)
        if vertical:
            mask[int(y) - 130:int(y) + 130, int(x) - 11:int(x) + 11] = True
        else:
            mask[int(y) - 11:int(y) + 11, int(x) - 130:int(x) + 130] = True
        return _fit_bar(_pixels(mask)), _pixels(mask)

    blades = [bar_at(200.0, 400.0, True), bar_at(780.0, 400.0, True)]
    assert _parallel_pair(blades, widths) is None
    near = [bar_at(200.0, 400.0, True), bar_at(420.0, 400.0, True)]  # 10 widths apart
    assert _parallel_pair(near, widths) == (0, 1)
    in_line = [bar_at(300.0, 400.0, False), bar_at(1000.0, 404.0, False)]  # 700 px along
    assert _parallel_pair(in_line, widths) == (0, 1)


def test_a_blade_seen_edge_on_does_not_set_the_level_of_steel():
    """Operating-room seed 25, view 1: a blade seen edge-on (15-20 mm of steel) stands alone
    far above the two pins, which must still pass as steel; without such a pair the
    strongest bar sets the level, so bone's far fainter bars stay out."""
    assert _steel_level(np.array([4.92, 1.85, 1.78, 1.24, 1.23])) == 1.85
    assert _steel_level(np.array([2.0, 1.9, 0.3, 0.25])) == 2.0
    assert _steel_level(np.array([2.0, 0.3, 0.25])) == 2.0  # the pins in one bar: bone stays out
    assert _steel_level(np.array([6.22, 1.22])) == 6.22


def _pin_shadow(start_mm: np.ndarray, axis: np.ndarray, length_mm: float, width_px: float) -> _Bar:
    """The bar a pin from ``start_mm`` along ``axis`` casts through a pinhole (f = 3000 px,
    principal point 512, 512): its axis projected, a pin's width added for its end discs."""
    ends = np.array([start_mm, start_mm + length_mm * axis])
    px = 3000.0 * ends[:, :2] / ends[:, 2:] + 512.0
    span = px[1] - px[0]
    return _Bar(px.mean(axis=0), span / np.linalg.norm(span), 0.5 * (np.linalg.norm(span) + width_px),
                0.5 * width_px)


def test_parallel_pins_seen_nearly_end_on_point_at_one_vanishing_point_alike():
    """Two parallel pins 50 mm apart, seen 8 deg off their axis: their shadows point at
    one vanishing point, each shaft the same share of its distance to it, while the
    distances differ with where each pin lies across the beam (views seed 24, view 1: 401
    and 231 px at the true pose, so a test of alike distances missed the pins)."""
    axis = np.array([0.12, -0.06, 1.0]) / np.linalg.norm([0.12, -0.06, 1.0])  # 8 deg off the beam
    pin_a = _pin_shadow(np.array([-60.0, 20.0, 700.0]), axis, 60.0, 22.0)
    pin_b = _pin_shadow(np.array([-10.0, 20.0, 700.0]), axis, 60.0, 22.0)
    assert _converging(pin_a, pin_b, 22.0) is not None
    shorter = _pin_shadow(np.array([-10.0, 20.0, 700.0]), axis, 30.0, 22.0)  # not the pair's length
    assert _converging(pin_a, shorter, 22.0) is None
    beside = _Bar(pin_a.centre + [0.0, 40.0], pin_a.direction, pin_a.half_length, pin_a.half_width)
    assert _converging(pin_a, beside, 22.0) is None  # parallel on the frame: no vanishing point


def _touching_pins(angle_deg: float) -> np.ndarray:
    """A label image, shadow 1: pin A (20 px wide, x = 50-450) with its head (36 px across)
    at x = 410-450, and pin B, 20 px wide and 400 px long, at ``angle_deg`` to A, from A's
    head's lower side (6 px below A's side where parallel). Shadow 2 lies apart."""
    labels = np.zeros((260, 700), np.int32)
    labels[90:110, 50:450] = 1
    labels[82:118, 410:450] = 1
    if angle_deg == 0.0:
        labels[116:136, 150:550] = 1
    else:
        a = np.radians(angle_deg)
        end = np.array([430.0, 126.0])
        start = end - 380.0 * np.array([np.cos(a), -np.sin(a)])
        b = np.zeros(labels.shape, np.uint8)
        cv2.line(b, (int(start[0]), int(start[1])), (int(end[0]), int(end[1])), 1, 20)
        labels[b > 0] = 1
    labels[200:220, 100:600] = 2
    return labels


def test_two_pins_side_by_side_touching_at_a_head_are_cut_apart():
    """Headed pins seed 7, view 2: A's head touched B's shaft, and the one shadow, notched by
    the slit between them, was split as two pins in line, one cut to a third of its length.
    Cut along the notch, each pin is a shadow of its own, whole."""
    labels = _touching_pins(0.0)
    widths = _PinWidths.of(ContourConfig(), 20.0)
    assert _split_notched(labels, labels > 0, 3, np.array([False, True, True]), widths, ContourConfig()) == 4
    bars = sorted((_fit_bar(_pixels(labels == k)) for k in (1, 3)), key=lambda bar: bar.centre[1])
    assert np.allclose(bars[0].centre, [250, 100], atol=6) and abs(2 * bars[0].half_length - 400) < 10
    assert np.allclose(bars[1].centre, [350, 126], atol=6) and abs(2 * bars[1].half_length - 400) < 10
    assert (labels == 2).sum() == 20 * 500  # the other shadow is left as it was


def test_two_pins_at_an_angle_touching_are_not_cut():
    """A wedge between two bars 30 deg apart is no slit between parallel pins."""
    labels = _touching_pins(30.0)
    before = labels.copy()
    widths = _PinWidths.of(ContourConfig(), 20.0)
    count = _split_notched(labels, labels > 0, 3, np.array([False, True, True]), widths, ContourConfig())
    assert count == 3 and np.array_equal(labels, before)
