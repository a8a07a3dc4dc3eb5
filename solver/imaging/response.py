"""Undo the C-arm's grey-level response from the frame's own quantum noise.

A C-arm may store its frames after a logarithmic response, a gamma and a window, so that
``-log(grey)`` is no longer attenuation: a log-stored frame read that way compresses the
bone's step to nothing. Whatever the (monotonic, pointwise) response ``g = f(I)``, the
detected quanta ``I`` are Poisson, so their square root has one constant noise SD at
every level: ``d sqrt(I) = dg / (2 sd(g))``, up to a constant factor (the detector's blur
and unsharp masking scale the noise alike at every level). Integrating ``1 / sd(g)``, read
from the frame, over the grey levels gives ``sqrt(I)`` up to that factor and an offset,
hence attenuation up to a constant. The offset (``sqrt(I)`` at the darkest level, cut off
by the C-arm's window) is fitted for the common logarithmic response, under which the
noise's SD is inversely proportional to ``sqrt(I)``.

A frame whose noise variance is linear in the grey level (raw frames, scatter added, low
dose), or rises with it below one stored level (a blurring detector's raw frames, whose
noise the levels' rounding makes stepwise), is linear in the quanta and left to the exact
``-log`` of its signal, unless that spans far less attenuation than any knee frame: then
its noise said nothing (8 bits quantise a log response's away) and it is read as
log-stored (:func:`frame_attenuation`).
"""

from __future__ import annotations

import cv2
import numpy as np

from slamtka.solver.imaging.field import attenuation

__all__ = ["frame_attenuation", "linearised_attenuation", "noise_by_level"]

_BINS = 48
_MIN_PER_BIN = 100
# A frame whose noise variance is this close to linear in the grey level (R^2) is linear
# in the quanta. Raw frames left 0.99-0.996 (scatter, low dose, flat panel); log or
# gamma-processed ones 0.74-0.83 (simulated operating-room frames).
_LINEAR_R2 = 0.95
# Of the range of sqrt(quanta): the offset below the darkest level when the logarithmic
# fit does not give one.
_FLOOR_SHARE = 0.05
# Attenuation between the field's 5th and 95th percentiles. A knee frame read right spans
# at least the first (the bone alone adds more; simulated frames, linear or linearised from
# their noise: 0.96-5.5); idealised frames span the second (2.3-2.4).
_LEAST_SPREAD = 0.9
# Under this many of its stored grey levels a frame's noise shows its rounding more than
# the quanta: the noise's SD, a median of whole quarter levels, moves in steps. A detector
# that blurs 1.5-2 px (a worn intensifier) smooths a raw frame's noise to 0.4-0.8 levels,
# and its variance, still rising with the level as the quanta's, is no longer linear in
# it (R^2 0.69-0.83): such a frame is raw (a log response's noise falls with the level).
_LEAST_NOISE_LEVELS = 1.0
_TYPICAL_SPREAD = 2.3


def noise_by_level(x: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Grey levels (bin centres, ascending) and the quantum noise's SD there, or None if
    unreadable.

    The noise is the pixel's departure from the mean of its four neighbours (edges are few;
    a per-bin median of absolute departures ignores them). Clipped pixels (a saturated
    detector, the C-arm's window) carry no noise and are left out."""
    # Every other row and column: as many pixels as the bins need, a quarter of the sort.
    # The neighbours wrap around the frame's sides (its rim is no inner pixel anyway).
    wrapped = np.pad(x, 1, mode="wrap")
    up, down = wrapped[0:-2:2, 1:-1:2], wrapped[2::2, 1:-1:2]
    left, right = wrapped[1:-1:2, 0:-2:2], wrapped[1:-1:2, 2::2]
    residual = x[::2, ::2] - 0.25 * (up + down + left + right)
    level = cv2.blur(x, (5, 5))
    inner = cv2.erode(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    if not inner.any():
        return None
    clipped = (x >= x.max(where=inner, initial=-np.inf)) | (x <= x.min(where=inner, initial=np.inf))
    inner &= cv2.dilate(clipped.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
    level, residual = level[::2, ::2][inner[::2, ::2]], residual[inner[::2, ::2]]
    if level.size < _BINS * _MIN_PER_BIN:
        return None
    edges = np.unique(np.percentile(level, np.linspace(0.5, 99.5, _BINS + 1)))
    if len(edges) < 8:
        return None
    # Bin numbers as bytes: their stable sort is a radix sort.
    which = np.clip(np.searchsorted(edges, level) - 1, 0, len(edges) - 2).astype(np.uint8)
    order = np.argsort(which, kind="stable")
    bounds = np.searchsorted(which[order], np.arange(len(edges)))
    centres, sds = [], []
    for b in range(len(edges) - 1):
        r = residual[order[bounds[b]:bounds[b + 1]]]
        if len(r) < _MIN_PER_BIN:
            continue
        centres.append(0.5 * (edges[b] + edges[b + 1]))
        sds.append(1.4826 * float(np.median(np.abs(r - np.median(r)))))
    sd = np.asarray(sds)
    if len(centres) < 8 or np.any(sd <= 0):
        return None
    # The SD is a smooth function of the level: a running mean over five bins.
    sd = np.convolve(np.pad(sd, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    return np.asarray(centres), sd


def linearised_attenuation(image: np.ndarray, valid: np.ndarray, sign: int) -> np.ndarray | None:
    """Attenuation (natural-log units, up to a constant) of a frame stored through a
    non-linear response, or None when the response is linear (or the noise unreadable).

    ``sign`` is the frame's polarity (+1: attenuating bodies dark)."""
    x = (sign * np.asarray(image)).astype(np.float32)
    noise = noise_by_level(x, valid)
    if noise is None:
        return None
    g, sd = noise
    variance = sd**2
    fit = np.polyfit(g, variance, 1)
    residual = variance - np.polyval(fit, g)
    r2 = 1.0 - float(residual @ residual) / max(float(((variance - variance.mean()) ** 2).sum()), 1e-12)
    if fit[0] > 0 and (r2 >= _LINEAR_R2 or sd.max() < _LEAST_NOISE_LEVELS * _grey_step(x, valid)):
        return None
    root = np.concatenate([[0.0], np.cumsum(np.diff(g) * 0.25 * (1.0 / sd[1:] + 1.0 / sd[:-1]))])
    k, offset = np.linalg.lstsq(np.column_stack([1.0 / sd, -np.ones_like(sd)]), root, rcond=None)[0]
    floor = float(offset) if k > 0 and 0 < offset < root[-1] else _FLOOR_SHARE * root[-1]
    # Beyond the binned levels the response goes on linearly in sqrt(quanta).
    low = (root[1] - root[0]) / max(g[1] - g[0], 1e-9)
    high = (root[-1] - root[-2]) / max(g[-1] - g[-2], 1e-9)
    s = np.interp(x, g, root)
    s = np.where(x < g[0], root[0] + (x - g[0]) * low, s)
    s = np.where(x > g[-1], root[-1] + (x - g[-1]) * high, s)
    return (-2.0 * np.log(np.maximum(s + floor, 0.5 * floor))).astype(np.float32)


def _grey_step(x: np.ndarray, valid: np.ndarray) -> float:
    """The step between the frame's stored grey levels (1 for whole levels, 257 for 8 bits
    spread over 16; near 0 for a frame of real numbers): the least gap between the
    distinct levels of a sample of the field."""
    levels = np.unique(x[valid][::31])
    return float(np.min(np.diff(levels))) if len(levels) > 1 else 0.0


def frame_attenuation(image: np.ndarray, valid: np.ndarray, outside: float, sign: int
                      ) -> tuple[np.ndarray, str]:
    """The frame's attenuation and how its response was read: "linear" (``-log`` of the
    signal over the no-signal level ``outside``), "linearised from the noise" or
    "log-stored, read from its spread"."""
    linearised = linearised_attenuation(image, valid, sign)
    if linearised is not None:
        return linearised, "linearised from the noise"
    read_linear = attenuation(image, outside, sign)
    log_stored = _log_stored_attenuation(image, valid, sign, read_linear)
    if log_stored is not None:
        return log_stored, "log-stored, read from its spread"
    return read_linear, "linear"


def _log_stored_attenuation(image: np.ndarray, valid: np.ndarray, sign: int,
                            read_linear: np.ndarray) -> np.ndarray | None:
    """Attenuation (up to a constant) of a frame that, read as linear in the quanta, spans
    less than any knee frame can, or None when ``read_linear`` spans enough.

    Its noise said linear because it could not say anything: stored in 8 bits, a log
    response's noise is quantised away (operating-room processing seed 23: 0.4 between
    the field's 5th and 95th percentiles, half the leg then taken for air). It is read as
    the common log-stored frame, attenuation linear in the grey level, at the spread of a
    frame read right; the response's own scale is lost with its noise."""
    low, high = np.percentile(read_linear[valid][::7], [5.0, 95.0])
    if high - low >= _LEAST_SPREAD:
        return None
    grey = -sign * np.asarray(image, np.float32)
    low, high = np.percentile(grey[valid][::7], [5.0, 95.0])
    if high <= low:
        return None
    return ((grey - low) * (_TYPICAL_SPREAD / (high - low))).astype(np.float32)
