"""The model-guided bone edge search: edges are found along the model outline's normals,
placed on the true outline, in undistorted pixels, and only where the frame shows bone."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from slamtka.solver.imaging.edges import BoneEdgeSearch, edges_along_normals, gradient

SIZE, CENTRE, RADIUS = 400, np.array([200.0, 210.0]), 100.0
SHIFT = np.array([6.0, -4.0])  # raw = ideal + SHIFT: a "distortion" whose inverse is exact


def _disk_frame() -> np.ndarray:
    """The smoothed attenuation of a bone seen as a disk (path length growing like a
    sphere's chord) over flat tissue, in raw pixels."""
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    r2 = (u - CENTRE[0]) ** 2 + (v - CENTRE[1]) ** 2
    attenuation = (0.4 * np.sqrt(np.maximum(RADIUS ** 2 - r2, 0.0)) / RADIUS).astype(np.float32)
    return cv2.GaussianBlur(attenuation, (0, 0), 1.5)


def _footprint(centre: np.ndarray, radius: float) -> np.ndarray:
    mask = np.zeros((SIZE, SIZE), np.uint8)
    cv2.circle(mask, tuple(int(round(c)) for c in centre), int(round(radius)), 1, -1)
    return mask


def _search(visible: np.ndarray | None = None) -> BoneEdgeSearch:
    search = BoneEdgeSearch.of_frame(_disk_frame(), np.ones((SIZE, SIZE), bool) if visible is None
                                     else visible, 0.015, 0.0)
    return replace(search, distort=lambda p: p + SHIFT, undistort=lambda p: p - SHIFT)


def test_edges_are_found_on_the_outline_from_a_model_off_by_more_than_the_mask_search():
    """The model's outline lies 10 px outside the bone (and the image is offset by its
    distortion): within a 14 px reach the edges found lie on the true outline."""
    ideal_centre = CENTRE - SHIFT
    edges, share = _search()(_footprint(ideal_centre + [4.0, 3.0], RADIUS + 7.0), 14.0)
    radii = np.linalg.norm(edges - ideal_centre, axis=1)
    assert len(edges) > 200 and share > 0.95
    assert np.median(np.abs(radii - RADIUS)) < 0.7
    assert np.percentile(np.abs(radii - RADIUS), 95) < 1.5


def test_no_edge_is_found_beyond_the_reach_or_where_the_frame_hides_the_bone():
    ideal_centre = CENTRE - SHIFT
    assert _search()(_footprint(ideal_centre, RADIUS + 25.0), 14.0)[1] == 0.0
    hidden = np.ones((SIZE, SIZE), bool)
    hidden[:, :int(CENTRE[0])] = False  # the left half: metal, say
    edges, share = _search(hidden)(_footprint(ideal_centre, RADIUS), 6.0)
    assert len(edges) > 50 and share > 0.95  # of the visible half
    assert np.all(edges[:, 0] + SHIFT[0] >= CENTRE[0] - 1.0)


@pytest.mark.parametrize("reach", [4.0, 12.0])
def test_an_empty_footprint_finds_nothing(reach):
    edges, share = _search()(np.zeros((SIZE, SIZE), np.uint8), reach)
    assert edges.shape == (0, 2) and share == 0.0


def test_a_recorded_search_finds_the_same_edges():
    """A run's recording holds each view's search, so that ``replay --resolve`` seeks the
    bone's edges as the run did."""
    search = _search()
    doc = json.loads(json.dumps(search.to_json()))
    again = BoneEdgeSearch.from_json(doc, search.distort, search.undistort)
    footprint = _footprint(CENTRE - SHIFT + [4.0, 3.0], RADIUS + 7.0)
    (edges, share), (edges_again, share_again) = search(footprint, 14.0), again(footprint, 14.0)
    assert np.array_equal(edges, edges_again) and share == share_again
    with pytest.raises(ValueError, match="needs 100 values"):
        BoneEdgeSearch.from_json({**doc, "shape": [10, 10]}, search.distort, search.undistort)


def test_a_search_over_a_reduced_frame_finds_the_edges_on_the_frames_own_pixels():
    """A large frame is extracted reduced (contours.WORKING_SIDE_PX); its search keeps the
    reduced attenuation and is asked, and answers, in the frame's own pixels. It finds the
    outline as the search over the whole frame does, and a recording keeps the scale."""
    reduced = cv2.resize(_disk_frame(), (SIZE // 2, SIZE // 2), interpolation=cv2.INTER_AREA)
    search = replace(BoneEdgeSearch.of_frame(reduced, np.ones(reduced.shape, bool), 0.015, 0.0),
                     distort=lambda p: p + SHIFT, undistort=lambda p: p - SHIFT, scale=2.0)
    ideal_centre = CENTRE - SHIFT
    footprint = _footprint(ideal_centre + [4.0, 3.0], RADIUS + 7.0)
    edges, share = search(footprint, 14.0)
    radii = np.linalg.norm(edges - ideal_centre, axis=1)
    assert len(edges) > 200 and share > 0.95
    assert np.median(np.abs(radii - RADIUS)) < 1.0
    again = BoneEdgeSearch.from_json(json.loads(json.dumps(search.to_json())), search.distort, search.undistort)
    assert again.scale == 2 and np.array_equal(again(footprint, 14.0)[0], edges)
    # Beyond the reach in the frame's own pixels, nothing (not twice as far in reduced ones).
    assert search(_footprint(ideal_centre, RADIUS + 25.0), 14.0)[1] == 0.0


def test_edges_are_sought_along_more_normals_than_one_remap_takes():
    """cv2.remap takes fewer than 32767 rows: a noisy 2048 px frame's 40,000 bone contour
    points failed ("contour extraction failed unexpectedly"). The same points searched all
    at once and in two halves give the same edges."""
    grad = gradient(_disk_frame())
    angles = np.linspace(0.0, 2.0 * np.pi, 40_000, endpoint=False)
    normals = np.column_stack([np.cos(angles), np.sin(angles)])
    points = CENTRE + (RADIUS + 3.0) * normals
    whole = edges_along_normals(grad, points, normals, 6.0, 0.015)
    halves = [edges_along_normals(grad, points[part], normals[part], 6.0, 0.015)
              for part in (slice(0, 20_000), slice(20_000, None))]
    assert len(whole[0]) > 39_000
    for k in range(4):
        assert np.array_equal(whole[k], np.concatenate([half[k] for half in halves]), equal_nan=True)
