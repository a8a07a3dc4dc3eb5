"""Sub-pixel edges along normals: where a blurred outline lies in a frame.

Both the first, model-free extraction (:mod:`.contours`, which starts from the boundary of
a mask) and the model-guided search (:class:`BoneEdgeSearch`, which starts from the bone
model's projected outline at the poses the solver reached) place an edge the same way:
along the outward normal, where the attenuation falls fastest, corrected for the blur of
the imaging chain measured in the frame itself.
"""

from __future__ import annotations

import base64
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BoneEdgeSearch", "bone_edges", "edges_along_normals", "gradient", "kept_in", "outline_with_normals",
           "to_frame_pixels", "to_working_pixels"]

Gradient = tuple[np.ndarray, np.ndarray]  # d/du and d/dv of the smoothed attenuation (float32)


def outline_with_normals(mask: np.ndarray, min_length: int) -> tuple[np.ndarray, np.ndarray]:
    """Boundary pixels of a mask (outer boundaries and holes) and their outward unit normals."""
    found = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)[0]
    points, normals = [], []
    for contour in found:
        p = contour.reshape(-1, 2).astype(float)
        if len(p) < min_length:
            continue
        k = 3
        tangent = np.roll(p, -k, axis=0) - np.roll(p, k, axis=0)
        norm = np.linalg.norm(tangent, axis=1, keepdims=True)
        n = np.column_stack([tangent[:, 1], -tangent[:, 0]]) / np.maximum(norm, 1e-9)
        points.append(p)
        normals.append(n)
    if not points:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p, n = np.vstack(points), np.vstack(normals)
    # Orient normals away from the mask.
    probe = np.round(p + 2.5 * n).astype(int)
    h, w = mask.shape
    probe = np.clip(probe, 0, [w - 1, h - 1])
    flip = mask[probe[:, 1], probe[:, 0]] > 0
    n[flip] *= -1
    return p, n


# A silhouette's path length grows like sqrt(depth) inside the outline; blurred by a
# Gaussian of sigma, the steepest fall of that profile sits _SQRT_PEAK sigma inside the true
# outline and the sharpest bend (its onset) _SQRT_ONSET sigma outside it.
_SQRT_PEAK, _SQRT_ONSET = 0.765, 0.551


_REMAP_ROWS = 32_000  # cv2.remap takes maps of fewer than 32767 rows (points, here)


def _sampled(image: np.ndarray, map_u: np.ndarray, map_v: np.ndarray) -> np.ndarray:
    """``image`` interpolated at (``map_u``, ``map_v``), a row per point, in blocks of rows
    that cv2.remap takes (a noisy 2048 px frame gave 40,000 bone contour points)."""
    return np.vstack([cv2.remap(image, map_u[i:i + _REMAP_ROWS], map_v[i:i + _REMAP_ROWS],
                                cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                      for i in range(0, len(map_u), _REMAP_ROWS)])


def edges_along_normals(grad: tuple[np.ndarray, np.ndarray], points: np.ndarray,
                         normals: np.ndarray, search: float, min_strength: float,
                         search_in: float | None = None,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Along each outward normal, where the image falls fastest within ``search_in`` (default
    ``search``) px inwards and ``search`` px outwards.

    Returns the sub-pixel edge positions, their normals, the fall per pixel there, and the
    distance from the steepest fall out to the sharpest bend of the profile (NaN when not
    measurable), which measures the blur of the imaging chain.
    """
    empty = np.zeros((0, 2))
    if len(points) == 0:
        return empty, empty, np.zeros(0), np.zeros(0)
    step = 0.25
    s = np.arange(-(search if search_in is None else search_in), search + step / 2, step)
    samples = points[:, None, :] + s[None, :, None] * normals[:, None, :]
    map_u, map_v = samples[..., 0].astype(np.float32), samples[..., 1].astype(np.float32)
    gx, gy = (_sampled(component, map_u, map_v) for component in grad)
    drop = -(gx * normals[:, 0:1] + gy * normals[:, 1:2])  # positive where the image falls outwards
    peak = np.argmax(drop, axis=1)
    best = np.clip(peak, 1, len(s) - 2)
    rows = np.arange(len(points))
    y0, y1, y2 = drop[rows, best - 1], drop[rows, best], drop[rows, best + 1]
    curvature = y0 - 2 * y1 + y2
    shift = np.where(curvature < 0, 0.5 * (y0 - y2) / np.where(curvature < 0, curvature, -1), 0.0)
    position = s[best] + np.clip(shift, -1, 1) * step
    # The bend: where the fall weakens fastest, outside the peak.
    weakening = -np.diff(drop, axis=1)
    outside = np.arange(len(s) - 1)[None, :] >= peak[:, None]
    bend_index = np.argmax(np.where(outside, weakening, -np.inf), axis=1)
    bend = np.where(bend_index < len(s) - 2, s[bend_index] + step / 2 - position, np.nan)
    ok = (peak > 0) & (peak < len(s) - 1) & (y1 >= min_strength)
    return ((points + position[:, None] * normals)[ok], normals[ok], y1[ok], bend[ok])


def bone_edges(grad: Gradient, points: np.ndarray, normals: np.ndarray, search_out: float,
               search_in: float, min_strength: float, offset_px: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """Bone edges found along the outward ``normals`` of ``points`` (``search_in`` px
    inwards, ``search_out`` outwards), placed on the outline under the frame's own blur;
    also the fall per pixel at each and the blur's sigma (px).

    Two estimates of the outline are exact for a sqrt-onset profile: the steepest fall
    moved out by _SQRT_PEAK sigma, and the point's sharpest bend moved in by _SQRT_ONSET
    sigma. Where the profile departs from the model (a plateau seen edge-on rises more
    gently) their mean is closer to the outline than either (median, p95 and coverage on
    simulated frames)."""
    edges, normals, strength, bend = edges_along_normals(grad, points, normals, search_out,
                                                         min_strength, search_in)
    sigma = float(np.nanmedian(bend) / (_SQRT_PEAK + _SQRT_ONSET)) if np.any(np.isfinite(bend)) else 0.0
    from_bend = np.where(np.isfinite(bend), bend - _SQRT_ONSET * sigma, _SQRT_PEAK * sigma)
    shift = 0.5 * (_SQRT_PEAK * sigma + from_bend) + offset_px
    return edges + shift[:, None] * normals, strength, sigma


def gradient(smooth: np.ndarray) -> Gradient:
    """The per-pixel derivatives of a smoothed image (float32), as edges are placed on them."""
    return (cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0,
            cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0)


def kept_in(points: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """The points (N, 2) whose nearest pixel lies in the mask ``allowed``."""
    h, w = allowed.shape
    pix = np.round(points).astype(int)
    inside = (pix[:, 0] >= 0) & (pix[:, 1] >= 0) & (pix[:, 0] < w) & (pix[:, 1] < h)
    ok = np.zeros(len(points), bool)
    ok[inside] = allowed[pix[inside, 1], pix[inside, 0]]
    return points[ok]


def _unchanged(points: np.ndarray) -> np.ndarray:
    return points


# Every this many pixels of the model's outline an edge is sought (the solver thins its
# contours to 6 px anyway).
_GUIDED_SPACING_PX = 2


@dataclass(frozen=True)
class BoneEdgeSearch:
    """The bone's edges in one frame near where the bone model's outline says they are.

    The first extraction takes as bone what soft tissue does not reach; at low dose, over
    a femur or under a C-arm's processing the tissue can reach past a gently rising edge,
    and the mask's boundary then lies 10-20 px inside the outline, beyond the reach of its
    normal search. Once the solver has the views on the bone, the model's projected outline
    says where the edge is: each of its points is searched along its own normal, as far as
    the solver's pose may still be off, for the steepest fall of the frame's attenuation.
    Only edges where the frame shows the bone (in the field, clear of metal, text, pins'
    shadows and the skin) are returned.

    It keeps the frame's smoothed attenuation in half precision, over its median, and the
    region as bits (a service holds many frames' contours while views wait for their run:
    2.1 MB a frame, not the 9 MB of its gradient and mask), and takes the gradient again
    when asked."""

    attenuation: np.ndarray  # (H, W) float16: the smoothed attenuation over its median, raw pixels
    visible_bits: np.ndarray  # np.packbits of the (H, W) mask over raw pixels where a bone edge may be kept
    min_strength: float  # attenuation fall per pixel at an accepted edge
    offset_px: float  # outward shift of bone edges (ContourConfig.bone_edge_offset_px)
    distort: Callable[[np.ndarray], np.ndarray] = _unchanged  # undistorted (ideal) to raw pixels
    undistort: Callable[[np.ndarray], np.ndarray] = _unchanged  # raw to ideal pixels
    scale: float = 1.0  # raw pixels a side to one of ``attenuation`` (a large frame reduced)

    @staticmethod
    def of_frame(smooth: np.ndarray, visible: np.ndarray, min_strength: float,
                 offset_px: float) -> BoneEdgeSearch:
        """The search over a frame's smoothed attenuation (float32, raw pixels)."""
        level = np.float32(np.median(smooth[::4, ::4]))
        return BoneEdgeSearch((smooth - level).astype(np.float16), np.packbits(visible.ravel()),
                              min_strength, offset_px)

    def to_json(self) -> dict:
        """The search as JSON (the attenuation compressed, the region as packed bits, both in
        base64), so that a recorded run can be solved again as it was."""
        def packed(data: bytes) -> str:
            return base64.b64encode(zlib.compress(data, 6)).decode("ascii")

        return {"shape": list(self.attenuation.shape),
                "attenuation_float16": packed(np.ascontiguousarray(self.attenuation, "<f2").tobytes()),
                "visible_bits": packed(self.visible_bits.tobytes()),
                "min_strength": self.min_strength, "offset_px": self.offset_px, "scale": self.scale}

    @staticmethod
    def from_json(doc: dict, distort: Callable[[np.ndarray], np.ndarray],
                  undistort: Callable[[np.ndarray], np.ndarray]) -> BoneEdgeSearch:
        """The search :meth:`to_json` wrote, through the given distortion."""
        def unpacked(text: str) -> bytes:
            return zlib.decompress(base64.b64decode(text))

        h, w = (int(n) for n in doc["shape"])
        attenuation = np.frombuffer(unpacked(doc["attenuation_float16"]), "<f2")
        bits = np.frombuffer(unpacked(doc["visible_bits"]), np.uint8)
        if attenuation.size != h * w or bits.size * 8 < h * w:
            raise ValueError(f"a bone edge search of {h} x {w} px needs {h * w} values")
        return BoneEdgeSearch(attenuation.astype(np.float16).reshape(h, w), bits[:-(-h * w // 8)].copy(),
                              float(doc["min_strength"]), float(doc["offset_px"]), distort, undistort,
                              float(doc.get("scale", 1.0)))

    def __call__(self, footprint: np.ndarray, reach_px: float) -> tuple[np.ndarray, float]:
        """Edge pixels (N, 2), undistorted, within ``reach_px`` of the outline of
        ``footprint`` (the model's projection, a mask over the undistorted image), and the
        share of the outline's visible samples that found one."""
        outline, normals = outline_with_normals(footprint, 30)
        outline, normals = outline[::_GUIDED_SPACING_PX], normals[::_GUIDED_SPACING_PX]
        raw = self.distort(outline) if len(outline) else outline
        # The normals carried through the distortion, which turns them only slightly.
        raw_normals = self.distort(outline + normals) - raw if len(outline) else normals
        raw_normals /= np.maximum(np.linalg.norm(raw_normals, axis=1, keepdims=True), 1e-9)
        raw = to_working_pixels(raw, self.scale)
        visible = np.unpackbits(self.visible_bits, count=self.attenuation.size).reshape(
            self.attenuation.shape).astype(bool)
        seen = len(kept_in(raw, visible))
        if seen == 0:
            return np.zeros((0, 2)), 0.0
        reach = reach_px / self.scale
        edges, _, _ = bone_edges(gradient(self.attenuation.astype(np.float32)), raw, raw_normals,
                                 reach, reach, self.min_strength, self.offset_px)
        edges = to_frame_pixels(kept_in(edges, visible), self.scale)
        return (self.undistort(edges) if len(edges) else np.zeros((0, 2))), len(edges) / seen


def to_frame_pixels(points: np.ndarray, scale: float) -> np.ndarray:
    """Pixel positions (N, 2) on a frame reduced ``scale`` times a side, on the frame itself
    (pixel centres: a reduced pixel's centre is that of the frame's pixels it averages)."""
    return (points + 0.5) * scale - 0.5 if scale != 1.0 and len(points) else points


def to_working_pixels(points: np.ndarray, scale: float) -> np.ndarray:
    """The inverse of :func:`to_frame_pixels`."""
    return (points + 0.5) / scale - 0.5 if scale != 1.0 and len(points) else points
