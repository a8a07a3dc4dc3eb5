"""A case's frames, stored alike by one C-arm, are read with the polarity the clear ones show."""

from __future__ import annotations

import numpy as np

from slamtka.solver.imaging.contours import ExtractedContours, agreed_polarity


def _read(polarity: str, decisive: bool) -> ExtractedContours:
    empty = np.zeros((0, 2))
    return ExtractedContours(empty, empty, empty, {"polarity": polarity, "polarity_decisive": decisive})


def test_a_frame_read_from_weak_cues_takes_the_polarity_its_clear_partner_shows():
    """Shutters seeds 14 and 23: view 1's periphery said little and a collimator blade's
    edge passed for steel of the other sign; view 2's periphery said "dark" clearly."""
    assert agreed_polarity([_read("bright", False), _read("dark", True)]) == "dark"
    assert agreed_polarity([_read("bright", False), None, _read("dark", True)]) == "dark"


def test_a_frame_whose_polarity_could_not_be_told_is_tried_again_as_its_clear_partner_reads():
    """The real tibia's operating-room seed 18: view 1 showed no steel standing out and was
    not extracted; view 2 read "bright" clearly (and view 1, read so, shows both pins)."""
    assert agreed_polarity([None, _read("bright", True)]) == "bright"


def test_a_frame_whose_polarity_could_not_be_told_takes_its_partners_weak_reading():
    """The operating room without the surgeon's views, seed 1: view 1, a processed
    flat-panel frame with its pins off the centre, showed no steel standing out; view 2
    read "dark" from weak cues only. Read so, view 1 shows both pins and the case measures.
    Weak readings that disagree say nothing."""
    assert agreed_polarity([None, _read("dark", False)]) == "dark"
    assert agreed_polarity([None, _read("dark", False), _read("dark", False)]) == "dark"
    assert agreed_polarity([None, _read("dark", False), _read("bright", False)]) is None


def test_frames_that_agree_or_that_nothing_clear_contradicts_are_left_as_read():
    assert agreed_polarity([_read("dark", False), _read("dark", True)]) is None
    assert agreed_polarity([_read("bright", False), _read("dark", False)]) is None
    assert agreed_polarity([_read("bright", True), _read("dark", True)]) is None  # both clear: each stands
