"""Exact shortcuts of the field helpers: the components and holes OpenCV's statistics would
give, and the opening of broad metal over its box as over the whole frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slamtka.solver.imaging.contours import ContourConfig, _broad_opaque
from slamtka.solver.imaging.field import components, fill_holes, remove_overlays


def _speckle(seed: int, share: float = 0.45) -> np.ndarray:
    return np.random.default_rng(seed).random((97, 131)) < share


@pytest.mark.parametrize("connectivity", [4, 8])
def test_components_are_those_of_opencv_with_their_areas(connectivity):
    mask = _speckle(1)
    count, labels, areas = components(mask, connectivity)
    expected = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=connectivity)
    assert count == expected[0]
    assert np.array_equal(labels, expected[1])
    assert np.array_equal(areas, expected[2][:, cv2.CC_STAT_AREA])


def test_only_enclosed_holes_are_filled_and_only_small_ones_when_asked():
    mask = np.zeros((60, 80), bool)
    mask[10:50, 10:70] = True
    mask[20:25, 20:25] = False  # a small hole (25 px)
    mask[30:45, 40:60] = False  # a large one (300 px)
    mask[0:10, 30:35] = True  # a bar to the frame's border: the gap beside it is no hole
    filled = fill_holes(mask)
    assert filled[10:50, 10:70].all() and not filled[0:10, 0:30].any()
    small_only = fill_holes(mask, max_area=100)
    assert small_only[20:25, 20:25].all() and not small_only[30:45, 40:60].any()


def _broad_reference(A: np.ndarray, valid: np.ndarray, config: ContourConfig) -> np.ndarray:
    """The opening of broad metal over the whole frame, as it was first written."""
    sub = A[::2, ::2][valid[::2, ::2]]
    opaque = (valid & (A > float(np.median(sub)) + config.opaque_excess)).astype(np.uint8)
    radius = int(config.pin_width_px[1])
    inner = cv2.distanceTransform(opaque, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) > radius
    grown = cv2.distanceTransform((~inner).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return cv2.dilate((grown <= radius).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


@pytest.mark.parametrize("blades", [(), ((20, 160, 30, 150),), ((0, 60, 0, 300), (150, 300, 210, 300))])
def test_broad_metal_over_its_box_is_the_whole_frames_opening(blades):
    A = np.random.default_rng(2).normal(1.0, 0.05, (300, 300)).astype(np.float32)
    for top, bottom, left, right in blades:
        A[top:bottom, left:right] += 3.0
    A[100:110, 150:290] += 3.0  # a pin: narrower than the opening's disk
    valid = np.ones(A.shape, bool)
    config = ContourConfig()
    broad = _broad_opaque(A, valid, config)
    assert broad.any() == bool(blades) and not broad[105, 200]
    assert np.array_equal(broad, _broad_reference(A, valid, config))


def test_a_clipped_pin_broken_by_noise_is_no_burned_in_text():
    """A window that clipped an inverted frame's pin leaves it at the extreme level only in
    patches between the noise, with an unsharp-masking halo around it: no patch is a stroke
    of text, while text at that level beside it still is."""
    rng = np.random.default_rng(3)
    image = 300.0 + rng.normal(0.0, 8.0, (200, 300))
    pin = (slice(90, 112), slice(40, 260))
    image[pin] = 1033.0 - np.abs(rng.normal(0.0, 20.0, image[pin].shape))  # up to ~6% below the top
    image[86:90, 40:260] -= 150.0  # the halo beside it
    image[112:116, 40:260] -= 150.0
    image[20:50, 20:23] = image[20:23, 20:40] = 1023.0  # an "F" of burned-in text
    image[34:37, 20:35] = 1023.0
    image = np.clip(image, 0.0, 1023.0).round().astype(np.uint16)
    assert 0.2 < np.mean(image[pin] == 1023) < 0.6  # clipped in patches
    _, strokes = remove_overlays(image)
    assert not strokes[pin].any()
    assert strokes[20:50, 20:23].all()
