"""Simulated C-arm radiographs of a posed knee: the imaging half of the simulated C-arm.

Physics, in the order the signal meets it:

1. Beer-Lambert line integrals along every pixel ray: a soft-tissue envelope around the
   leg, tibia and fibula (a cortical shell of ``cortical_thickness_mm`` denser than the
   cancellous interior) and the two steel pins. Each body's path
   length comes from exact rasterisation of its closed mesh (``raster.path_lengths``); bone
   and steel attenuate by their excess over the soft tissue they displace. The operating
   room's other bodies (femur, patella, retractors) and its detector and processing are
   added by ``solver.imaging.operating_room`` (``extra`` bodies, ``exposure``).
2. Focal-spot blur (Gaussian, ``focal_blur_px``) of the expected photon count, then quantum
   noise (Poisson, ``photons`` expected quanta per pixel with no object in the beam).
3. The intensifier: its distortion (``solver.imaging.distortion``) warps the image, its
   output blur (``detector_blur_px``) and vignetting (brightness falling as
   ``1 - vignetting * (r / R)^2`` towards the rim) follow, and nothing outside the circular
   field of view is imaged.
4. Digitisation to ``bits_stored`` bits, pixel value proportional to the detected intensity
   (DICOM Pixel Intensity Relationship LIN, MONOCHROME2: bone and metal dark), or inverted
   (``invert``) as some C-arms display and store it.

Linear attenuation coefficients are effective values for a filtered ~70 kVp C-arm beam
(about 45 keV effective): water 0.02/mm, cortical bone 0.05/mm, cancellous bone 0.028/mm,
stainless steel 0.9/mm.

Ground truth: the outer outline of tibia with fibula and the outline of each pin, traced on
the meshes (``solver.silhouette.ContourGenerator``), in ideal and in distorted pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import trimesh

from slamtka.sim.raster import path_lengths
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.plan import Plan
from slamtka.solver.silhouette import ContourGenerator

__all__ = ["XRayParams", "XRayScene", "Radiograph", "render_radiograph", "render_bodies",
           "default_distortion", "Body"]

# Simplified copy used for the inner (endosteal) bone surface: it is not an observed edge.
_INNER_SURFACE_FACES = 8000
_TRUTH_SPACING_PX = 0.25


def default_distortion(camera: Camera) -> Distortion:
    """A typical 23 cm intensifier: ~5% pincushion and ~3 px S-twist at the rim."""
    radius = camera.fov_radius_px or max(camera.width, camera.height) / 2.0
    return Distortion((camera.width - 1) / 2.0, (camera.height - 1) / 2.0, radius,
                      k1=0.045, k2=0.008, t1=0.006, t2=-0.002)


@dataclass(frozen=True)
class XRayParams:
    """Documented imaging parameters; defaults describe a mobile C-arm with a 23 cm intensifier."""

    mu_soft_per_mm: float = 0.020
    mu_cortical_per_mm: float = 0.050
    mu_cancellous_per_mm: float = 0.028
    mu_steel_per_mm: float = 0.9
    cortical_thickness_mm: float = 2.0
    # Soft-tissue envelope: elliptical cross-sections (z, half-width x, half-depth y) in the
    # tibia's anatomical frame, centred at envelope_centre_mm (x, y): the calf lies posterior.
    envelope_profile_mm: tuple[tuple[float, float, float], ...] = (
        (150.0, 62.0, 58.0), (40.0, 58.0, 50.0), (-60.0, 55.0, 50.0), (-180.0, 52.0, 48.0),
        (-300.0, 36.0, 32.0), (-400.0, 30.0, 28.0))
    envelope_centre_mm: tuple[float, float] = (0.0, -14.0)
    photons: float = 4000.0
    focal_blur_px: float = 0.6
    detector_blur_px: float = 0.7
    vignetting: float = 0.3
    bits_stored: int = 12
    dark_level: float = 30.0  # grey level of no signal
    invert: bool = False
    distortion: Distortion | None = None  # None: default_distortion(camera)

    def __post_init__(self) -> None:
        if not 8 <= self.bits_stored <= 16:
            raise ValueError(f"bits stored {self.bits_stored} is outside 8-16")
        if self.photons <= 0:
            raise ValueError("photons per pixel must be positive")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting {self.vignetting} must be in [0, 1)")
        if min(self.focal_blur_px, self.detector_blur_px, self.cortical_thickness_mm) < 0:
            raise ValueError("blur and cortical thickness must not be negative")


@dataclass(frozen=True)
class Body:
    """A closed mesh in some frame and its attenuation in excess of soft tissue (1/mm)."""

    vertices: np.ndarray
    faces: np.ndarray
    mu_excess: float
    smooth: bool = False  # no edge that is measured: rendered at half resolution, upsampled


def _closed(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    if not mesh.is_watertight:
        raise ValueError(f"{name} mesh is not closed; X-ray path lengths need a closed surface")
    if mesh.volume < 0:
        mesh = mesh.copy()
        mesh.invert()
    return mesh


def _inner_surface(mesh: trimesh.Trimesh, thickness: float) -> trimesh.Trimesh:
    """The endosteal surface: a simplified copy moved ``thickness`` inwards along its normals."""
    inner = mesh
    if len(mesh.faces) > _INNER_SURFACE_FACES:
        inner = mesh.simplify_quadric_decimation(face_count=_INNER_SURFACE_FACES)
    return trimesh.Trimesh(inner.vertices - thickness * inner.vertex_normals, inner.faces,
                           process=False)


def _envelope(params: XRayParams) -> trimesh.Trimesh:
    """Closed elliptical tube through the profile's cross-sections (anatomical frame)."""
    around = 72
    profile = np.array(sorted(params.envelope_profile_mm))
    z = np.arange(profile[0, 0], profile[-1, 0] + 1e-9, 10.0)
    ax, ay = np.interp(z, profile[:, 0], profile[:, 1]), np.interp(z, profile[:, 0], profile[:, 2])
    theta = np.arange(around) * 2.0 * np.pi / around
    cx, cy = params.envelope_centre_mm
    rings = np.stack([cx + ax[:, None] * np.cos(theta), cy + ay[:, None] * np.sin(theta),
                      np.broadcast_to(z[:, None], (len(z), around))], axis=-1).reshape(-1, 3)
    vertices = np.vstack([rings, [[cx, cy, z[0]], [cx, cy, z[-1]]]])
    i = np.arange(len(z) - 1)[:, None] * around
    j = np.arange(around)[None, :]
    a, b = i + j, i + (j + 1) % around
    faces = [np.stack([a, b, b + around], -1).reshape(-1, 3), np.stack([a, b + around, a + around], -1).reshape(-1, 3)]
    bottom, top = len(rings), len(rings) + 1
    last = (len(z) - 1) * around
    faces.append(np.column_stack([np.full(around, bottom), (j[0] + 1) % around, j[0]]))
    faces.append(np.column_stack([np.full(around, top), last + j[0], last + (j[0] + 1) % around]))
    mesh = trimesh.Trimesh(vertices, np.vstack(faces), process=True)
    mesh.fix_normals()
    return _closed(mesh, "soft-tissue envelope")


@dataclass
class XRayScene:
    """The per-plan meshes of a radiograph, built once (offset surfaces, envelope, contours)."""

    params: XRayParams
    bone: list[Body]  # tibia frame
    anatomy: list[Body]  # anatomical frame (the soft-tissue envelope)
    pin: Body  # pin frame
    T_tibia_anat: Pose
    bone_outline: ContourGenerator
    pin_outline: ContourGenerator

    @staticmethod
    def from_plan(plan: Plan, params: XRayParams = XRayParams()) -> XRayScene:
        soft = params.mu_soft_per_mm
        bone = []
        bone_meshes = [m.to_trimesh() for m in plan.bone_meshes()]
        for name, mesh in zip(("tibia", "fibula"), bone_meshes):
            mesh = _closed(mesh, name)
            bone.append(Body(mesh.vertices, mesh.faces, params.mu_cortical_per_mm - soft))
            if params.cortical_thickness_mm > 0:
                inner = _inner_surface(mesh, params.cortical_thickness_mm)
                bone.append(Body(inner.vertices, inner.faces,
                                 params.mu_cancellous_per_mm - params.mu_cortical_per_mm))
        envelope = _envelope(params)
        anatomy = [Body(envelope.vertices, envelope.faces, soft, smooth=True)]
        pin = _closed(plan.pin_mesh.to_trimesh(), "pin")
        return XRayScene(
            params, bone, anatomy, Body(pin.vertices, pin.faces, params.mu_steel_per_mm - soft),
            plan.landmarks.T_tibia_anat(),
            ContourGenerator.from_mesh(trimesh.util.concatenate(bone_meshes)),
            ContourGenerator.from_mesh(pin))


@dataclass
class Radiograph:
    """A rendered frame and its ground truth (pixels with origin at the top-left pixel centre)."""

    image: np.ndarray  # (H, W) uint16
    bits_stored: int
    camera: Camera
    distortion: Distortion
    silhouettes: dict[str, np.ndarray] = field(default_factory=dict)  # distorted pixels


def render_bodies(bodies: list[tuple[Body, Pose]], camera: Camera, origin: np.ndarray,
                  width: int, height: int) -> np.ndarray:
    """Line integral (sum of mu * path length) on a canvas whose pixel (0, 0) is at ``origin``."""
    total = np.zeros((height, width), np.float32)
    cx, cy = camera.cx - origin[0], camera.cy - origin[1]
    for body, T_cam_body in bodies:
        vertices = T_cam_body.apply(body.vertices)
        if body.smooth:
            # Half-resolution pixel centres sit at (u + 0.5) / 2 - 0.5, as cv2.resize expects.
            half = path_lengths(vertices, body.faces, camera.fx / 2, camera.fy / 2,
                                (cx + 0.5) / 2 - 0.5, (cy + 0.5) / 2 - 0.5,
                                -(-width // 2), -(-height // 2))
            lengths = cv2.resize(half, (2 * half.shape[1], 2 * half.shape[0]),
                                 interpolation=cv2.INTER_LINEAR)[:height, :width]
        else:
            lengths = path_lengths(vertices, body.faces, camera.fx, camera.fy, cx, cy, width, height)
        total += body.mu_excess * lengths
    return total


def _canvas(camera: Camera, distortion: Distortion) -> tuple[np.ndarray, int, int]:
    """Ideal-image canvas (origin, width, height) covering every pixel the frame shows."""
    w, h = camera.width, camera.height
    border = np.concatenate([
        np.column_stack([np.arange(w), np.zeros(w)]), np.column_stack([np.arange(w), np.full(w, h - 1)]),
        np.column_stack([np.zeros(h), np.arange(h)]), np.column_stack([np.full(h, w - 1), np.arange(h)])])
    ideal = np.vstack([distortion.undistort(border), [[0, 0], [w - 1, h - 1]]])
    lo = np.floor(ideal.min(axis=0)) - 3
    hi = np.ceil(ideal.max(axis=0)) + 3
    return lo, int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(image, (0, 0), sigma) if sigma > 0 else image


def expose(line_integral: np.ndarray, origin: np.ndarray, camera: Camera, params: XRayParams,
           distortion: Distortion, rng: np.random.Generator) -> np.ndarray:
    """Detector image (uint16) of an ideal-canvas line integral: noise, intensifier, digitiser."""
    expected = params.photons * np.exp(-line_integral.astype(np.float64))
    counts = rng.poisson(_blur(expected, params.focal_blur_px)).astype(np.float32)
    image = _blur(distortion.warp(counts, camera.width, camera.height, tuple(origin)),
                  params.detector_blur_px)
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    r = np.hypot(u - distortion.centre_u, v - distortion.centre_v)
    fov = camera.fov_radius_px or np.inf
    image = image * (1.0 - params.vignetting * (r / distortion.radius) ** 2)
    full_scale = (1 << params.bits_stored) - 1
    grey = params.dark_level + image * (0.85 * full_scale - params.dark_level) / params.photons
    # The field edge is the intensifier's (blurred) aperture, not a hard cut.
    aperture = np.clip(fov - r + 0.5, 0.0, 1.0)
    grey = params.dark_level + (grey - params.dark_level) * aperture
    if params.invert:
        grey = full_scale - grey
    return np.clip(np.round(grey), 0, full_scale).astype(np.uint16)


def _solid_interior(generator: ContourGenerator, T_cam_body: Pose, camera: Camera) -> np.ndarray:
    """The footprint interior of :meth:`ContourGenerator.interior`, with gaps narrower than
    a footprint pixel closed: a radiograph does not resolve the edges of such a gap (between
    the fibula and the tibia where they nearly touch, for one), so its folds are no outline.
    """
    kernel = np.ones((3, 3), np.uint8)
    footprint = cv2.morphologyEx(generator.footprint(T_cam_body, camera), cv2.MORPH_CLOSE, kernel)
    return cv2.erode(footprint, kernel)


Exposure = Callable[[np.ndarray, np.ndarray, Camera, XRayParams, Distortion, np.random.Generator],
                    np.ndarray]


def render_radiograph(plan: Plan, T_cam_tibia: Pose, T_tibia_pins: list[Pose] | tuple[Pose, ...],
                      camera: Camera, params: XRayParams = XRayParams(),
                      rng: np.random.Generator | None = None,
                      scene: XRayScene | None = None,
                      extra: Sequence[tuple[Body, Pose]] = (),
                      exposure: Exposure = expose) -> Radiograph:
    """Render one C-arm frame of the plan's leg with its pins, and its ground-truth outlines.

    ``scene`` (from :meth:`XRayScene.from_plan`) saves rebuilding the meshes for every frame.
    ``extra`` bodies (with their ``T_cam_body``) are in the beam but not measured (the
    operating room's femur, retractors); ``exposure`` turns the line integral into the
    stored frame (:func:`expose`, or the operating room's detector and processing).
    """
    rng = rng if rng is not None else np.random.default_rng()
    scene = scene if scene is not None else XRayScene.from_plan(plan, params)
    distortion = params.distortion or default_distortion(camera)
    T_cam_anat = T_cam_tibia @ scene.T_tibia_anat
    bodies = [(b, T_cam_tibia) for b in scene.bone] + [(b, T_cam_anat) for b in scene.anatomy]
    bodies += [(scene.pin, T_cam_tibia @ T) for T in T_tibia_pins] + list(extra)
    origin, width, height = _canvas(camera, distortion)
    line_integral = render_bodies(bodies, camera, origin, width, height)
    image = exposure(line_integral, origin, camera, params, distortion, rng)

    outlines = {"bone": (scene.bone_outline, T_cam_tibia)}
    outlines.update({f"pin{i + 1}": (scene.pin_outline, T_cam_tibia @ T)
                     for i, T in enumerate(T_tibia_pins)})
    distorted = {}
    for label, (generator, T) in outlines.items():
        if label == "bone":
            points = generator.outline_points(T, camera, _TRUTH_SPACING_PX,
                                              interior=_solid_interior(generator, T, camera))
        else:
            # A pin is convex: every contour generator is on its outline. (The footprint
            # test that drops a bone's interior folds is too coarse for a 20 px wide shaft.)
            points = generator.outline_points(T, camera, _TRUTH_SPACING_PX, outer_only=False)
        uv = camera.project(T.apply(points))
        observed = distortion.distort(uv) if len(uv) else uv
        distorted[label] = observed[camera.in_field(observed, 2.0)] if len(uv) else uv
    return Radiograph(image, params.bits_stored, camera, distortion, distorted)
