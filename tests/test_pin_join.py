"""A pin's shadow cut where its excess dips is joined again; pins end to end are not."""

from __future__ import annotations

import numpy as np

from slamtka.solver.imaging.contours import _join_in_line

_ROW, _HALF_WIDTH = 60, 8  # a horizontal pin's shadow, 17 px wide
_GAP = slice(150, 180)  # the columns between the two pieces


def _cut_bar(gap_excess: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A bar of excess 0.7 over columns 20-379, ``gap_excess`` over the gap, labelled as two
    pieces on either side of it (what growing to half its peak leaves when the gap is under
    it); with the labels' pin-likeness and typical excess."""
    rng = np.random.default_rng(0)
    excess = rng.normal(0.0, 0.02, (120, 400)).astype(np.float32)
    rows = slice(_ROW - _HALF_WIDTH, _ROW + _HALF_WIDTH + 1)
    excess[rows, 20:380] += 0.7
    excess[rows, _GAP] += gap_excess - 0.7
    labels = np.zeros(excess.shape, np.int32)
    labels[rows, 20:_GAP.start] = 1
    labels[rows, _GAP.stop:380] = 2
    return labels, np.array([False, True, True]), excess, np.array([0.0, 0.7, 0.7])


def test_a_bar_cut_where_its_excess_dipped_is_one_shadow_again():
    """Scatter seeds 1, 10, 11, 25: a pin's excess fell to 0.36-0.45 beside the air, under
    half its peak, and its shadow was cut in two there."""
    labels, good, excess, typical = _cut_bar(0.4)
    assert _join_in_line(labels, good, excess, typical)
    assert good.tolist() == [False, True, False]
    assert (labels[_ROW - _HALF_WIDTH + 1:_ROW + _HALF_WIDTH, 20:380] == 1).all()
    assert not labels[:_ROW - _HALF_WIDTH - 3].any() and not labels[_ROW + _HALF_WIDTH + 4:].any()


def test_pins_end_to_end_with_tissue_between_stay_two_shadows():
    labels, good, excess, typical = _cut_bar(0.0)
    before = labels.copy()
    assert not _join_in_line(labels, good, excess, typical)
    assert good.tolist() == [False, True, True]
    assert np.array_equal(labels, before)


def test_bars_side_by_side_or_across_each_other_are_not_joined():
    labels, good, excess, typical = _cut_bar(0.4)
    labels[labels == 2] = 0
    labels[90:107, 180:380] = 2  # parallel, 38 px lower: the other pin beside it
    assert not _join_in_line(labels, good, excess, typical)
    labels[labels == 2] = 0
    labels[5:115, 200:217] = 2  # across it
    assert not _join_in_line(labels, good, excess, typical)
