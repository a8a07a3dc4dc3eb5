"""Varied frames for the robustness tests of contour extraction: whatever a C-arm, a
PACS or a damaged file may hand over, derived from a rendered frame or made up outright."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import cv2
import numpy as np


def _window(image: np.ndarray, bits: int, lo_pct: float, hi_pct: float) -> np.ndarray:
    lo, hi = np.percentile(image, [lo_pct, hi_pct])
    top = (1 << bits) - 1
    return np.clip((image.astype(float) - lo) / max(hi - lo, 1e-9) * top, 0, top).astype(
        np.uint8 if bits <= 8 else np.uint16)


def _log(image: np.ndarray) -> np.ndarray:
    return _window(np.log1p(image.astype(float)), 12, 0.1, 99.9)


def _unsharp(image: np.ndarray) -> np.ndarray:
    f = image.astype(np.float32)
    return np.clip(2.0 * f - cv2.GaussianBlur(f, (0, 0), 8.0), 0, 4095).astype(np.uint16)


def _gamma(image: np.ndarray) -> np.ndarray:
    return _window(np.power(image.astype(float), 0.5), 12, 0, 100)


def _flat_panel(image: np.ndarray) -> np.ndarray:
    """The central square of the field, rescaled to the frame: no dark corners."""
    h, w = image.shape
    c = image[h // 2 - h // 3: h // 2 + h // 3, w // 2 - w // 3: w // 2 + w // 3]
    return cv2.resize(c, (w, h), interpolation=cv2.INTER_LINEAR)


TRANSFORMS: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "as rendered": lambda im, rng: im,
    "inverted": lambda im, rng: 4095 - im,
    "8-bit window": lambda im, rng: _window(im, 8, 1, 99),
    "16-bit": lambda im, rng: (im.astype(np.uint32) * 16).astype(np.uint16),
    "log response": lambda im, rng: _log(im),
    "log inverted": lambda im, rng: 4095 - _log(im),
    "unsharp masked": lambda im, rng: _unsharp(im),
    "gamma": lambda im, rng: _gamma(im),
    "saturated": lambda im, rng: np.clip(im.astype(np.int32) * 4, 0, 4095).astype(np.uint16),
    "flat panel": lambda im, rng: _flat_panel(im),
    "flat panel inverted": lambda im, rng: 4095 - _flat_panel(im),
    "cropped corner": lambda im, rng: im[: im.shape[0] // 3, : im.shape[1] // 3],
    "tiny": lambda im, rng: cv2.resize(im, (64, 64), interpolation=cv2.INTER_AREA),
    "shifted signed": lambda im, rng: im.astype(np.int16) - 2048,
    "float": lambda im, rng: im.astype(np.float32) / 4095.0,
    "half float": lambda im, rng: im.astype(np.float16),  # scaled to 16 bits it overflows
    "noisy": lambda im, rng: np.clip(im + rng.normal(0, 300, im.shape), 0, 4095).astype(np.uint16),
    "half blank": lambda im, rng: np.where(np.arange(im.shape[1])[None, :] < im.shape[1] // 2, im, 0).astype(im.dtype),
}


def made_up_frames(rng: np.random.Generator) -> Iterator[tuple[str, np.ndarray]]:
    """Frames with nothing of a knee in them."""
    yield "uniform", np.full((256, 256), 1000, np.uint16)
    yield "all zero", np.zeros((128, 160), np.uint16)
    yield "all max 8-bit", np.full((128, 128), 255, np.uint8)
    yield "white noise", rng.integers(0, 4096, (256, 256)).astype(np.uint16)
    yield "gradient", np.tile(np.linspace(0, 4095, 300), (200, 1)).astype(np.uint16)
    yield "one bright pixel", np.pad(np.array([[4095]], np.uint16), 100)
    yield "binary", (rng.random((200, 200)) > 0.5).astype(np.uint8)
    yield "bright disc", cv2.circle(np.zeros((300, 300), np.uint16), (150, 150), 120, 3000, -1)
    yield "disc with bar", cv2.line(cv2.circle(np.full((300, 300), 30, np.uint16), (150, 150), 130, 3000, -1),
                                    (60, 150), (240, 170), 200, 12)
    yield "nan", np.full((100, 100), np.nan, np.float32)
    yield "one row", np.zeros((1, 500), np.uint16)
    yield "colour", np.zeros((100, 100, 3), np.uint8)
