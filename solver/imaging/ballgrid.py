"""Steel balls of a calibration plate in a frame, and their place on the plate's grid.

Balls are found in the frame's attenuation (any polarity, inside the circular field,
vignetting removed by a local median background) as compact blobs of the expected size;
blobs cut by the rim of the field or merged with other metal are refused. Their centres are
attenuation-weighted centroids.

The grid: neighbouring balls give the two lattice directions; integer grid coordinates are
propagated from a central ball, each step predicted from the last observed step, so
perspective and distortion do not break it and missing balls are simply absent. A blob that
is no ball (a speck, dust) is left out rather than spoiling the frame: one that contradicts
its neighbours is skipped, and one that continues the lattice beyond the plate's extent is
cut off by the rows x cols window holding the most balls.

The plate is symmetric and transparent, so a frame alone fixes its balls' grid coordinates
only up to the eight symmetries of the square (and, when whole rows are missing, a shift):
:func:`placements` lists them; the calibration picks the one that fits the plate it knows.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from slamtka.solver.imaging.field import attenuation, field_of_view

__all__ = ["GridError", "detect_balls", "match_grid", "placements"]

_STARTS = 5  # central balls tried as the seed of the lattice (one may be a speck)
_NEIGHBOURS = 6  # of which pairs are tried as the lattice steps
_MAX_STEP_COSINE = 0.7  # the two steps at least ~45 degrees apart
# The eight symmetries of a square grid, as 2x2 integer maps of (col, row).
_SYMMETRIES = [np.array(m) for m in (
    [[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
    [[1, 0], [0, -1]], [[-1, 0], [0, 1]], [[0, 1], [1, 0]], [[0, -1], [-1, 0]])]


class GridError(ValueError):
    """No usable ball grid in a frame, with the reason."""


def detect_balls(image: np.ndarray, ball_diameter_px: tuple[float, float] = (8.0, 60.0),
                 polarity: str = "auto", min_contrast: float = 0.25) -> np.ndarray:
    """Centres (N, 2) of ball shadows: compact blobs of a plausible size, not cut by the rim."""
    centre, radius, outside, sign, _ = field_of_view(np.asarray(image), polarity, "phantom")
    A = attenuation(image, outside, sign)
    h, w = A.shape
    v, u = np.mgrid[0:h, 0:w]
    r = np.hypot(u - centre[0], v - centre[1])
    lit = r < (radius if radius is not None else np.inf) - 1.0
    A = np.where(lit, A, np.median(A[lit])).astype(np.float32)
    # Background at a scale several balls wide (median ignores the balls themselves).
    small = cv2.resize(A, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(small, [1, 99])
    q = np.clip((small - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    k = int(ball_diameter_px[1] / 4) | 1
    background = cv2.medianBlur(q, max(5, 2 * k + 1)).astype(np.float32) / 255 * (hi - lo) + lo
    excess = A - cv2.resize(background, (w, h), interpolation=cv2.INTER_LINEAR)
    blobs = (excess > min_contrast) & lit
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(blobs.astype(np.uint8), connectivity=8)
    d_lo, d_hi = ball_diameter_px
    area = stats[:, cv2.CC_STAT_AREA].astype(float)
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    fill = area / np.maximum(bw * bh, 1)
    round_ = (np.abs(bw - bh) <= 0.35 * np.maximum(bw, bh)) & (fill > 0.6)
    sized = (area >= np.pi / 4 * d_lo**2) & (area <= np.pi / 4 * d_hi**2)
    # A blob touching the rim of the field is partly hidden: its centroid is biased.
    far = np.sqrt(area / np.pi) + 3.0
    inside = np.linalg.norm(centroids - centre, axis=1) + far < (radius if radius is not None else np.inf)
    keep = round_ & sized & inside
    keep[0] = False
    index = np.nonzero(keep)[0]
    if len(index) == 0:
        return np.zeros((0, 2))
    weights = np.where(blobs, excess, 0.0)
    mass = ndimage.sum(weights, labels, index)
    cu = ndimage.sum(weights * u, labels, index) / mass
    cv = ndimage.sum(weights * v, labels, index) / mass
    return np.column_stack([cu, cv])


def _propagate(points: np.ndarray, start: int, a: np.ndarray, b: np.ndarray,
               spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Lattice coordinates grown from ``start`` with first steps ``a`` and ``b``; points
    contradicting the lattice are skipped."""
    coords = {start: (0, 0)}
    basis = {start: (a, b)}
    queue = [start]
    taken = {(0, 0): start}
    while queue:
        i = queue.pop(0)
        ci, (ai, bi) = coords[i], basis[i]
        for step, delta in ((ai, (1, 0)), (-ai, (-1, 0)), (bi, (0, 1)), (-bi, (0, -1))):
            target = (ci[0] + delta[0], ci[1] + delta[1])
            guess = points[i] + step
            j = int(np.argmin(np.linalg.norm(points - guess, axis=1)))
            if np.linalg.norm(points[j] - guess) > 0.3 * spacing or j in coords or target in taken:
                continue
            observed = points[j] - points[i]
            new_a = observed * delta[0] if delta[0] else ai
            new_b = observed * delta[1] if delta[1] else bi
            coords[j], basis[j], taken[target] = target, (new_a, new_b), j
            queue.append(j)
    index = np.array(list(coords))
    return index, np.array([coords[i] for i in index])


def _window(index: np.ndarray, grid: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """The balls inside the rows x cols window (either orientation) that holds the most."""
    grid = grid - grid.min(axis=0)
    best = None
    for w, h in {(cols, rows), (rows, cols)}:
        for ou in range(max(1, grid[:, 0].max() + 2 - w)):
            for ov in range(max(1, grid[:, 1].max() + 2 - h)):
                inside = ((grid[:, 0] >= ou) & (grid[:, 0] < ou + w)
                          & (grid[:, 1] >= ov) & (grid[:, 1] < ov + h))
                if best is None or inside.sum() > best.sum():
                    best = inside
    kept = grid[best]
    return index[best], kept - kept.min(axis=0)


def match_grid(points: np.ndarray, rows: int, cols: int, min_balls: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid coordinates of detected balls: (indices into ``points``, (K, 2) integer (col, row)).

    Blobs that are not on the lattice, or lie beyond the plate's extent, are left out. Raises
    :class:`GridError` when fewer than ``min_balls`` balls form a grid.
    """
    if len(points) < min_balls:
        raise GridError(f"only {len(points)} balls found, need {min_balls}")
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    central = np.argsort(np.linalg.norm(points - np.median(points, axis=0), axis=1))[:_STARTS]
    best = None
    for start in central:
        # The lattice steps: two of the nearest neighbours at a clear angle (a speck among
        # them gives a small lattice, which loses to the right one).
        steps = points[np.argsort(d[start])[:_NEIGHBOURS]] - points[start]
        unit = steps / np.linalg.norm(steps, axis=1, keepdims=True)
        cosine = np.abs(unit @ unit.T)
        for i, j in zip(*np.nonzero(np.triu(cosine < _MAX_STEP_COSINE, 1))):
            index, grid = _window(*_propagate(points, int(start), steps[i], steps[j], spacing), rows, cols)
            # Most balls; on a tie the squarer pair of steps (not a sheared labelling).
            score = (len(index), -cosine[i, j])
            if best is None or score > best[0]:
                best = score, index, grid
    if best is None or len(best[1]) < min_balls:
        raise GridError(f"only {0 if best is None else len(best[1])} balls form a grid, need {min_balls}")
    return best[1], best[2]


def placements(grid: np.ndarray, rows: int, cols: int,
               overhang: int = 2) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every placement of a frame's grid coordinates (K, 2) on the rows x cols plate.

    Each is (ball index row * cols + col, or -1 for a point beyond the plate (K,), M (2, 2)
    integer symmetry, shift (2,) in grid steps) with plate grid coordinate = M @ frame
    coordinate + shift. A placement may leave up to ``overhang`` steps of the frame's grid
    beyond the plate: blobs continuing the lattice past its edge (specks) are no balls.
    The placements that keep every point on the plate come first.
    """
    inside_first: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    overhanging: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for M in _SYMMETRIES:
        g = grid @ M.T
        low = g.min(axis=0)
        span = g.max(axis=0) - low + 1
        for ou in range(-overhang, cols - span[0] + 1 + overhang):
            for ov in range(-overhang, rows - span[1] + 1 + overhang):
                placed = g + np.array([ou, ov]) - low
                on = (placed[:, 0] >= 0) & (placed[:, 0] < cols) & (placed[:, 1] >= 0) & (placed[:, 1] < rows)
                if not on.any():
                    continue
                ball = np.where(on, placed[:, 1] * cols + placed[:, 0], -1)
                (inside_first if on.all() else overhanging).append((ball, M, np.array([ou, ov]) - low))
    return inside_first + overhanging
