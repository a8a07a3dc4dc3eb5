"""Simulated cases: a tibia on the table, two pins placed as a surgeon would, two C-arm views.

Used by tests, benchmarks and the demo. The simulation knows the ground truth; it is written
to a separate file that the solver never reads. Contours are traced on the full-resolution
meshes (the solver uses a simplified copy), then Gaussian pixel noise is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from slamtka.solver.anatomy import plane_normal_from_angles
from slamtka.solver.block import block_axes, bone_entry_mm, pin_pose
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, look_at, rotation_about
from slamtka.solver.observations import ViewObservation
from slamtka.solver.plan import Plan
from slamtka.solver.problem import InitialGuess
from slamtka.solver.silhouette import ContourGenerator

__all__ = ["SimulationConfig", "SimulatedCase", "SimulationError", "simulate_case", "default_camera", "perturb",
           "segmentation_error"]

# A mobile C-arm: ~1000 mm source to detector, 1024 px over a 23 cm image intensifier,
# knee at the isocentre ~620 mm from the source.
SOURCE_TO_DETECTOR_MM = 1000.0
SOURCE_TO_ISOCENTRE_MM = 620.0
DETECTOR_FIELD_MM = 230.0
DETECTOR_PIXELS = 1024


def default_camera(pixels: int | None = None) -> Camera:
    """The simulated C-arm's camera, its detector ``pixels`` a side (default
    :data:`DETECTOR_PIXELS`; a flat panel's 1536 or 2048 px keep the same field)."""
    return Camera.from_geometry(SOURCE_TO_DETECTOR_MM, DETECTOR_FIELD_MM,
                                DETECTOR_PIXELS if pixels is None else pixels)


class SimulationError(RuntimeError):
    """The simulator cannot build this case (e.g. its random pin line misses the bone):
    a study skips the seed and goes on."""


ROT_SD_PER_LEVEL_RAD = 0.1
TRANS_SD_PER_LEVEL_MM = 20.0


@dataclass(frozen=True)
class SimulationConfig:
    """One simulated case; :meth:`at_level` gives the evaluation protocol's noise levels."""

    view_angles_deg: tuple[float, ...] = (-30.0, 30.0)  # about the leg axis, 0 = AP
    noise_px: float = 2.0
    init_rot_sd_rad: float = 0.1
    init_trans_sd_mm: float = 20.0
    # Error of the encoders' C-arm motion from the first view to each other one, about the knee.
    encoder_rot_sd_deg: float = 0.5
    encoder_trans_sd_mm: float = 2.0
    outline_spacing_px: float = 1.0
    # CT segmentation error: the bone the X-rays see differs from the plan's mesh by a smooth
    # displacement along its normals with this SD (0: the protocol of docs/evaluation.md).
    segmentation_sd_mm: float = 0.0
    seed: int = 0
    detector_pixels: int | None = None  # a side of the detector (None: DETECTOR_PIXELS)

    @staticmethod
    def at_level(level: int, seed: int, noise_px: float = 2.0) -> SimulationConfig:
        """Initial-state noise of level 1..5 of docs/evaluation.md: rotations SD 0.1 rad x
        level, translations SD 20 mm x level, on the set-up and on each pin (the protocol's
        noise on 3D edge points has no counterpart: the solver seats them on their rays)."""
        return SimulationConfig(noise_px=noise_px, seed=seed,
                                init_rot_sd_rad=ROT_SD_PER_LEVEL_RAD * level,
                                init_trans_sd_mm=TRANS_SD_PER_LEVEL_MM * level)


@dataclass
class SimulatedCase:
    plan: Plan
    views: list[ViewObservation]
    initial: InitialGuess
    truth_T_cam_tibia: list[Pose]
    truth_T_tibia_pin: list[Pose]
    truth_ctr_deg: float
    truth_str_deg: float
    config: SimulationConfig


def perturb(T: Pose, rng: np.random.Generator, rot_sd: float, trans_sd: float,
            about: Pose | None = None) -> Pose:
    """``T`` moved by a random increment (Gaussian rotation vector and translation).

    The increment is applied in the frame ``about`` (given in T's source frame), e.g. the
    anatomical frame so that a view's error rotates the bone about the knee.
    """
    xi = np.concatenate([rng.normal(0.0, trans_sd, 3), rng.normal(0.0, rot_sd, 3)])
    if about is None:
        return T.retract(xi)
    return T @ about.retract(xi) @ about.inverse()


def _place_pins(plan: Plan, rng: np.random.Generator) -> tuple[list[Pose], float, float]:
    """Two parallel pins through an anteromedial cutting block, at a plausible CTR/STR."""
    lm = plan.landmarks
    T_tibia_anat = lm.T_tibia_anat()
    ctr = np.radians(rng.uniform(-4.0, 4.0))
    str_ = np.radians(rng.uniform(-1.0, 8.0))
    normal = plane_normal_from_angles(ctr, str_, lm.medial_sign)
    depth_below_plateau = rng.uniform(10.0, 25.0)
    plane_point = np.array([0.0, 0.0, -depth_below_plateau])
    posterior, across = block_axes(normal, np.radians(rng.uniform(-15.0, 15.0)))
    spacing = rng.uniform(20.0, 40.0)
    centre_offset = lm.medial_sign * rng.uniform(0.0, 12.0)  # anteromedial block
    sdf = plan.bone_model().sdf
    pins = []
    for offset in (centre_offset - spacing / 2, centre_offset + spacing / 2):
        start = plane_point + across * offset - posterior * 150.0  # far anterior, outside
        entry = bone_entry_mm(sdf, T_tibia_anat, start, posterior, 0.5)
        if entry is None:
            raise SimulationError("simulated pin line misses the bone; cannot place pins")
        # Drill 25-45 mm, but keep the tip at least 3 mm inside the bone.
        for drilled in np.linspace(rng.uniform(25.0, 45.0), 8.0, 40):
            tip_anat = start + (entry + drilled) * posterior
            if sdf.query(T_tibia_anat.apply(tip_anat[None]))[0][0] < -3.0:
                break
        pins.append(pin_pose(T_tibia_anat, tip_anat, posterior))
    return pins, float(np.degrees(ctr)), float(np.degrees(str_))


def _view_poses(plan: Plan, angles_deg: tuple[float, ...], rng: np.random.Generator) -> list[Pose]:
    """True ``T_cam_tibia`` of each view: a C-arm orbiting the leg axis around the knee."""
    T_tibia_anat = plan.landmarks.T_tibia_anat()
    # Patient set-up varies: the leg sits a little rotated and off the isocentre.
    setup = Pose(rotation_about(rng.normal(size=3), np.radians(rng.uniform(0.0, 5.0))),
                 rng.normal(0.0, 5.0, 3) + np.array([0.0, 0.0, -30.0]))
    poses = []
    for angle in angles_deg:
        direction = rotation_about([0.0, 0.0, 1.0], np.radians(angle)) @ np.array([0.0, -1.0, 0.0])
        eye = SOURCE_TO_ISOCENTRE_MM * direction  # source under the table, posterior
        T_iso_cam = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        T_anat_cam = setup @ T_iso_cam
        poses.append((T_tibia_anat @ T_anat_cam).inverse())
    return poses


def _observe(generator: ContourGenerator, T_cam_body: Pose, camera: Camera, outer_only: bool,
             config: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    points = generator.outline_points(T_cam_body, camera, config.outline_spacing_px,
                                      outer_only=outer_only)
    uv = camera.project(T_cam_body.apply(points))
    uv = uv + rng.normal(0.0, config.noise_px, uv.shape)
    return uv[camera.in_field(uv)]


# The segmentation error field: this many plane waves, wavelengths in this range (mm).
_SEGMENTATION_WAVES = 24
_SEGMENTATION_WAVELENGTH_MM = (15.0, 60.0)


def segmentation_error(mesh: trimesh.Trimesh, sd_mm: float,
                       rng: np.random.Generator) -> trimesh.Trimesh:
    """``mesh`` with every vertex moved along its normal by a smooth random field of SD
    ``sd_mm`` (a sum of plane waves of random direction, wavelength and phase): the true
    bone when the plan's mesh is a segmentation of it."""
    directions = rng.normal(size=(_SEGMENTATION_WAVES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    wavenumbers = 2 * np.pi / rng.uniform(*_SEGMENTATION_WAVELENGTH_MM, _SEGMENTATION_WAVES)
    phases = rng.uniform(0.0, 2 * np.pi, _SEGMENTATION_WAVES)
    vertices = np.asarray(mesh.vertices, float)
    waves = np.sin(vertices @ (directions * wavenumbers[:, None]).T + phases)
    displacement = sd_mm * waves.sum(axis=1) / np.sqrt(_SEGMENTATION_WAVES / 2)
    return trimesh.Trimesh(vertices + displacement[:, None] * mesh.vertex_normals, mesh.faces,
                           process=False)


def simulate_case(plan: Plan, config: SimulationConfig = SimulationConfig()) -> SimulatedCase:
    rng = np.random.default_rng(config.seed)
    camera = default_camera(config.detector_pixels)
    pins, ctr_deg, str_deg = _place_pins(plan, rng)
    views_true = _view_poses(plan, config.view_angles_deg, rng)
    bone = trimesh.util.concatenate([m.to_trimesh() for m in plan.bone_meshes()])
    if config.segmentation_sd_mm > 0:
        # Its own random stream, so the truth (pins, views) stays that of the same seed.
        bone = segmentation_error(bone, config.segmentation_sd_mm,
                                  np.random.default_rng([config.seed, 1]))
    bone_full = ContourGenerator.from_mesh(bone)
    pin_full = ContourGenerator.from_mesh(plan.pin_mesh.to_trimesh())
    views = []
    for k, T_cam_tibia in enumerate(views_true):
        contours = {"bone": _observe(bone_full, T_cam_tibia, camera, True, config, rng)}
        for label, T_tibia_pin in zip(("pin1", "pin2"), pins):
            contours[label] = _observe(pin_full, T_cam_tibia @ T_tibia_pin, camera, False,
                                       config, rng)
        views.append(ViewObservation(f"view{k + 1}", camera, contours))
    # The patient set-up (where the tibia lies in the C-arm) is the large, shared unknown;
    # the motion between views comes from the encoders with their own, smaller error.
    T_tibia_anat = plan.landmarks.T_tibia_anat()
    setup_error = perturb(Pose.identity(), rng, config.init_rot_sd_rad, config.init_trans_sd_mm,
                          T_tibia_anat)
    encoder_rad = np.radians(config.encoder_rot_sd_deg)
    initial = InitialGuess(
        tuple(T @ setup_error if k == 0 else
              perturb(T @ setup_error, rng, encoder_rad, config.encoder_trans_sd_mm, T_tibia_anat)
              for k, T in enumerate(views_true)),
        tuple(perturb(T, rng, config.init_rot_sd_rad, config.init_trans_sd_mm) for T in pins),
        (encoder_rad, config.encoder_trans_sd_mm),
    )
    return SimulatedCase(plan, views, initial, views_true, pins, ctr_deg, str_deg, config)
