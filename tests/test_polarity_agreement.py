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


def test_frames_that_agree_or_that_nothing_clear_contradicts_are_left_as_read():
    assert agreed_polarity([_read("dark", False), _read("dark", True)]) is None
    assert agreed_polarity([_read("bright", False), _read("dark", False)]) is None
    assert agreed_polarity([_read("bright", True), _read("dark", True)]) is None  # both clear: each stands
    assert agreed_polarity([None, _read("dark", True)]) is None
