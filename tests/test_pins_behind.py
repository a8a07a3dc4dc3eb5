"""A bar wider than one pin is the two pins seen one behind the other; a pin's bar is not."""

from __future__ import annotations

import numpy as np

from slamtka.sim.simulate import default_camera
from slamtka.solver.imaging.contours import (
    ONE_BAR_ONE_WIDE,
    ONE_BAR_TWO_WIDE,
    ContourConfig,
    ExtractedContours,
    _PinWidths,
    _split_one,
)
from slamtka.solver.imaging.edges import outline_with_normals
from slamtka.solver.observations import ViewObservation

_EXPECTED_WIDTH_PX = 20.0
_LEAST_LENGTH_PX = 250.0  # 0.4 of the ~600 px the initial pose foresees: longer than half the bar


def _split_bar(width_px: int, length_px: int) -> tuple | str | None:
    """What the split of one horizontal bar's shadow (no steps along its sides) gives."""
    labels = np.zeros((200, 700), np.int32)
    top = 100 - width_px // 2
    labels[top:top + width_px, 50:50 + length_px] = 1
    edges, normals = outline_with_normals(labels > 0, 10)
    widths = _PinWidths.of(ContourConfig(), _EXPECTED_WIDTH_PX)
    return _split_one(labels, np.array([1]), edges, normals, widths, _LEAST_LENGTH_PX, ContourConfig())


def test_a_bar_as_wide_as_two_pins_one_behind_the_other_is_both_pins():
    """Surgeon's views seeds 5 and 15, view 2 (lateral): the pins one behind the other cast
    one bar 1.3 pins wide, too even along its sides for a split into two pins. Both pins
    get all of its edges, for the fit to share out."""
    split = _split_bar(28, 450)
    assert isinstance(split, tuple)
    bars, overlap, edges = split
    assert overlap == "behind"
    assert bars[0] is bars[1]
    assert abs(2.0 * bars[0].half_width - 28) < 3 and abs(bars[0].direction[1]) < 1e-6
    assert len(edges) > 900  # the whole outline: 2 x (450 + 28) px


def test_a_bar_one_pin_wide_is_not_taken_for_both_pins():
    """The same bar a pin wide is one pin, its partner missed: fitted as both pins, each
    pin's line would lie in that bar's plane and the resection plane would be wrong. That
    it was seen is kept for the refusal's words (the pins exactly one behind the other, or
    one hidden)."""
    assert _split_bar(20, 450) == ONE_BAR_ONE_WIDE


def test_a_bar_too_short_for_the_pins_says_they_lie_one_behind_the_other():
    """A bar of two pins' width but shorter than a pin can be is not taken; that it was
    seen is kept for the refusal's words."""
    assert _split_bar(28, 200) == ONE_BAR_TWO_WIDE


def test_a_bar_one_pin_wide_but_shorter_than_a_pin_says_nothing_of_the_pins():
    """A pin-wide bar under a pin's least length is no evidence of both pins in it."""
    assert _split_bar(20, 200) is None


def test_a_bar_wider_only_where_pins_in_line_overlap_is_not_both_pins():
    """The real tibia's operating-room seed 26 at level 3: between two retractor blades, a
    piece of two pins in line, one overlapping the other's end, 44, 34 and 16 px wide along
    its thirds. Taken for both pins one behind the other, it was measured 5 deg off."""
    labels = np.zeros((200, 700), np.int32)
    columns = np.arange(50, 500)
    half_widths = np.round(np.linspace(8, 22, len(columns))).astype(int)  # 16 -> 44 px wide
    for x, half in zip(columns, half_widths):
        labels[100 - half:100 + half, x] = 1
    edges, normals = outline_with_normals(labels > 0, 10)
    widths = _PinWidths.of(ContourConfig(), _EXPECTED_WIDTH_PX)
    split = _split_one(labels, np.array([1]), edges, normals, widths, _LEAST_LENGTH_PX, ContourConfig())
    assert not isinstance(split, tuple) or split[1] != "behind"


def _observed(overlap: str) -> ViewObservation:
    """The solver's view of a split bar: pin 1 its left half, pin 2 its right half."""
    left = np.column_stack([np.arange(50.0, 300.0), np.full(250, 90.0)])
    right = np.column_stack([np.arange(300.0, 550.0), np.full(250, 90.0)])
    found = ExtractedContours(np.zeros((0, 2)), left, right, {"pins_overlap": overlap})
    return found.observation("v", default_camera(), lambda p: p, lambda p: p)


def test_a_bar_cut_in_its_middle_is_pooled_for_the_fit_to_share_out():
    """A bar with no step is cut in its middle as if the pins lay end to end, but they may
    lie each over all of it (retractors with the surgeon's views, seed 8, view 2): the cut
    is a guess, and the bar's edges go to the fit whole, once each, as a bar both pins lie
    behind. Pins whose steps or separate shadows say where each lies are not pooled."""
    pooled = _observed("coincident").pin_edges
    assert pooled is not None and len(pooled) == 500
    assert _observed("staggered").pin_edges is None  # steps say where each pin ends
    assert _observed("apart").pin_edges is None
