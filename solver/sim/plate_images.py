"""Simulated calibration phantom images: an acrylic plate carrying a grid of steel balls.

The plate is seen at many tilts through the same C-arm (same intrinsics, same intensifier
distortion), as a technician would hold it in the beam. Images may be inverted (a C-arm that
stores bone bright), may lose balls past the rim of the field, and may have a steel clamp
lying across part of the grid.

:func:`simulate_phantom_set` adds what a real set holds (issue 29): a plate whose balls sit
off the perfect grid (its manufacturing error), balls missing from the plate, dark specks
(dust or solder on the plate or the intensifier's input screen; one of them placed where the
grid would continue), frames without the phantom and byte copies of frames, and keeps the
truth (plate, poses) for the benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import trimesh

from slamtka.sim.xray import Body, XRayParams, expose, render_bodies
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, rotation_about
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.imaging.plate import PhantomSpec

__all__ = ["PhantomSet", "plate_offsets", "simulate_phantom_images", "simulate_phantom_set"]

_MU_STEEL = 0.9  # per mm, as XRayParams
_MU_ACRYLIC = 0.022


def _bodies(spec: PhantomSpec, clamp: bool, balls_mm: np.ndarray) -> list[Body]:
    ball = trimesh.creation.icosphere(subdivisions=2, radius=spec.ball_diameter_mm / 2.0)
    balls = trimesh.util.concatenate([ball.copy().apply_translation(p) for p in balls_mm])
    extent = max(spec.rows, spec.cols) * spec.pitch_mm + 20.0
    plate = trimesh.creation.box([extent, extent, spec.plate_thickness_mm])
    plate.apply_translation([0.0, 0.0, spec.plate_thickness_mm / 2.0 + spec.ball_diameter_mm / 2.0])
    bodies = [Body(balls.vertices, balls.faces, _MU_STEEL), Body(plate.vertices, plate.faces, _MU_ACRYLIC)]
    if clamp:
        bar = trimesh.creation.box([extent / 2.0, 10.0, 4.0])
        bar.apply_translation([extent / 4.0, spec.pitch_mm * (spec.rows - 1) / 2.0 - 2.0, -6.0])
        bodies.append(Body(bar.vertices, bar.faces, _MU_STEEL))
    return bodies


@dataclass
class PhantomSet:
    """Simulated phantom frames by name, with the truth they were made from."""

    names: list[str]
    images: list[np.ndarray]
    plate_mm: np.ndarray  # (rows*cols, 3) true ball centres in the plate frame; NaN: missing
    poses: dict[str, Pose] = field(default_factory=dict)  # T_cam_plate of frames showing it
    notes: dict[str, str] = field(default_factory=dict)  # what is special about a frame
    under_clamp: dict[str, np.ndarray] = field(default_factory=dict)  # balls (indices) the clamp hides


def _under_shadow(shadow: np.ndarray, centres_px: np.ndarray, radius_px: float) -> np.ndarray:
    """Which balls (projected ``centres_px``, N x 2) a shadow (line integral) touches: any of
    a ball's centre and four rim points lies in it."""
    ring = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * radius_px
    points = np.rint(centres_px[:, None, :] + ring[None]).astype(np.int64)
    h, w = shadow.shape
    inside = (points[..., 0] >= 0) & (points[..., 0] < w) & (points[..., 1] >= 0) & (points[..., 1] < h)
    values = shadow[np.clip(points[..., 1], 0, h - 1), np.clip(points[..., 0], 0, w - 1)]
    return np.any(inside & (values > 0), axis=1)


def _add_speck(line_integral: np.ndarray, centre_uv: np.ndarray, radius_px: float) -> None:
    """A small dense particle (chord profile of a steel sphere ``radius_px`` wide on the canvas)."""
    h, w = line_integral.shape
    r = int(np.ceil(radius_px)) + 1
    u0, v0 = int(round(centre_uv[0])), int(round(centre_uv[1]))
    if not (r <= u0 < w - r and r <= v0 < h - r):
        return
    v, u = np.mgrid[v0 - r: v0 + r + 1, u0 - r: u0 + r + 1]
    d2 = (u - centre_uv[0]) ** 2 + (v - centre_uv[1]) ** 2
    chord_px = 2.0 * np.sqrt(np.clip(radius_px**2 - d2, 0.0, None))
    # Thickness in mm as a ball of the same image size would have (about 0.15 mm per pixel).
    line_integral[v0 - r: v0 + r + 1, u0 - r: u0 + r + 1] += _MU_STEEL * 0.15 * chord_px


def plate_offsets(spec: PhantomSpec, rms_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Manufacturing error of a plate: independent 3-D ball offsets (N, 3) of RMS ``rms_mm``."""
    return rng.normal(0.0, rms_mm / np.sqrt(3.0), (spec.rows * spec.cols, 3))


def simulate_phantom_set(camera: Camera, distortion: Distortion, spec: PhantomSpec, count: int,
                         rng: np.random.Generator, plate_offsets_mm: np.ndarray | None = None,
                         missing_balls: tuple[int, ...] = (), specks: int = 0,
                         empty_frames: int = 0, duplicates: int = 0, max_tilt_deg: float = 40.0,
                         inverted_fraction: float = 0.25, clamp_fraction: float = 0.2,
                         params: XRayParams = XRayParams()) -> PhantomSet:
    """``count`` frames of the plate (``imgNN``), then ``empty_frames`` frames without it
    (``emptyNN``) and ``duplicates`` byte copies of earlier frames (``copyNN``).

    ``plate_offsets_mm``: the balls' offsets (rows*cols, 3) from the perfect grid (see
    :func:`plate_offsets`; the same ``rng`` state with and without them gives the same poses
    and noise, so a set can be compared with its perfect-plate twin); ``missing_balls``:
    grid indices (row * cols + col) absent from the plate; ``specks``: dark specks per frame,
    the first of every frame placed where the grid would continue beyond its last column.
    """
    plate = spec.points() + (0.0 if plate_offsets_mm is None else np.asarray(plate_offsets_mm, float))
    present = np.setdiff1d(np.arange(len(plate)), missing_balls)
    bodies = {clamp: _bodies(spec, clamp, plate[present]) for clamp in (False, True)}
    beyond = plate[spec.cols - 1:: spec.cols] + [spec.pitch_mm, 0.0, 0.0]  # the next column
    out = PhantomSet([], [], np.where(np.isin(np.arange(len(plate)), present)[:, None], plate, np.nan))
    for k in range(count):
        tilt_axis = rotation_about([0.0, 0.0, 1.0], rng.uniform(0, 2 * np.pi)) @ np.array([1.0, 0.0, 0.0])
        R = rotation_about(tilt_axis, np.radians(rng.uniform(5.0, max_tilt_deg))) @ \
            rotation_about([0.0, 0.0, 1.0], rng.uniform(-np.pi, np.pi))
        # Spread over the field so that balls also reach its rim, where distortion is largest.
        t = np.array([rng.normal(0.0, 20.0), rng.normal(0.0, 20.0), rng.uniform(560.0, 760.0)])
        clamp = bool(rng.random() < clamp_fraction)
        inverted = bool(rng.random() < inverted_fraction)
        # The exposure's own generator: its noise draws vary in number with the image, and the
        # next frame's pose must not depend on them (a set and its perfect-plate twin).
        noise = np.random.default_rng(rng.integers(1 << 62))
        pose = Pose(R, t)
        line_integral = render_bodies([(b, pose) for b in bodies[clamp]], camera,
                                      np.zeros(2), camera.width, camera.height)
        name = f"img{k:02d}"
        if clamp:
            shadow = render_bodies([(bodies[True][-1], pose)], camera, np.zeros(2), camera.width, camera.height)
            hidden = _under_shadow(shadow, camera.project(pose.apply(plate[present])),
                                   spec.ball_diameter_mm / 2.0 * camera.fx / t[2])
            out.under_clamp[name] = present[hidden]
        for s in range(specks):
            at = (camera.project(pose.apply(beyond[rng.integers(len(beyond))][None]))[0] if s == 0
                  else rng.uniform(0.2, 0.8, 2) * [camera.width, camera.height])
            _add_speck(line_integral, at, rng.uniform(5.0, 8.0))
        # The grid sits well inside the frame: the ideal canvas is the frame itself, and the
        # pincushion only pulls content inwards.
        out.names.append(name)
        out.images.append(expose(line_integral, np.zeros(2), camera,
                                 replace(params, invert=inverted), distortion, noise))
        out.poses[name] = pose
    for k in range(empty_frames):
        out.names.append(f"empty{k:02d}")
        out.images.append(expose(np.zeros((camera.height, camera.width), np.float32), np.zeros(2),
                                 camera, params, distortion, rng))
        out.notes[out.names[-1]] = "no phantom in the beam"
    for k in range(duplicates):
        source = out.names[k % max(count, 1)]
        out.names.append(f"copy{k:02d}")
        out.images.append(out.images[out.names.index(source)].copy())
        out.notes[out.names[-1]] = f"byte copy of {source}"
    return out


def simulate_phantom_images(camera: Camera, distortion: Distortion, spec: PhantomSpec, count: int,
                            rng: np.random.Generator, max_tilt_deg: float = 40.0,
                            inverted_fraction: float = 0.25, clamp_fraction: float = 0.2,
                            params: XRayParams = XRayParams()) -> list[np.ndarray]:
    """``count`` phantom frames (uint16) of a perfect plate at random tilts (up to
    ``max_tilt_deg``) and positions, some inverted and some with a steel clamp across the grid."""
    return simulate_phantom_set(camera, distortion, spec, count, rng, max_tilt_deg=max_tilt_deg,
                                inverted_fraction=inverted_fraction, clamp_fraction=clamp_fraction,
                                params=params).images
