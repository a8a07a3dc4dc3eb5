"""Pixel decoding honours BitsStored/HighBit, signed values and the inversion attributes."""

from __future__ import annotations

import numpy as np
import pytest
from service_testing import small_frame

from slamtka.service.frames import FrameError, decode_frame, encode_frame
from slamtka.service.pixel_layouts import layout_cases

CASES = layout_cases(encode_frame(small_frame()))


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_each_layout_decodes_to_the_image_or_is_refused_by_name(case):
    if case.expected is None:
        with pytest.raises(FrameError, match=case.error):
            decode_frame(case.dataset)
    else:
        frame = decode_frame(case.dataset)
        assert np.array_equal(frame.pixels, case.expected)
        assert frame.pixels.max() < 1 << frame.bits_stored
