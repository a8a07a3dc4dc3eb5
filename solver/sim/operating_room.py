"""What an operating-room frame of the proximal tibia shows besides tibia, fibula and pins.

Each nuisance is a named option of :class:`OperatingRoom`, drawn at random per case from
its own seed (:meth:`OperatingRoom.draw`), so that a study can take them one at a time or
all at once (:meth:`OperatingRoom.everything`); the idealised scene (no option) is the
control. In the order the signal meets them:

- ``femur``: the distal femur at the knee flexion of the tibial cut (70-110 deg), flexion
  swinging its shaft backwards from the knee, condyles on or behind the plateau;
- ``patella``: everted or subluxed laterally;
- ``retractors``: 1-3 bent steel blades (2 mm x 15-20 mm x 150 mm) at the medial and lateral
  plateau rim and behind it;
- ``marker``: a lead laterality letter lying on the detector;
- ``shutters``: collimator blades closing in from one or two sides;
- ``dose``: 300-4000 photons per pixel unattenuated;
- ``scatter``: a low-frequency scatter field, scatter-to-primary 0.3-1.0;
- ``flat_panel``: a flat-panel detector (square field, no distortion, no vignetting) instead
  of the image intensifier;
- ``processing``: the C-arm's own processing before storing: logarithmic response, unsharp
  masking, gamma, automatic windowing, stored inverted on some models, 8-16 bits stored;
- ``text``: burned-in annotation text;
- ``leg_width``: legs 90-160 mm wide at the knee (little or no air beside the skin);
- ``views``: the views a surgeon takes (AP within +-20 deg, lateral 60-90 deg, obliques);
- ``headed_pins``: pins with a head (the plan's pin model has none).

The femur and patella are real meshes (OpenSim body frames, metres: +x anterior, +y
proximal, +z right) read from ``mesh_folder``; without it a parametric femur stands in and
there is no patella.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np
import trimesh

from slamtka.sim.xray import (
    Body,
    Radiograph,
    XRayParams,
    XRayScene,
    _blur,
    _canvas,
    _envelope,
    default_distortion,
    render_bodies,
    render_radiograph,
)
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose, rotation_about
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.plan import Plan

__all__ = ["OperatingRoom", "RoomDraw", "RoomFrame", "NUISANCES", "room_bodies", "room_scene", "render_room",
           "expose_room", "view_angles"]

NUISANCES = ("femur", "patella", "retractors", "marker", "shutters", "dose", "scatter",
             "flat_panel", "processing", "text", "leg_width", "views", "headed_pins", "unsharpness")

# The detector's unsharpness, a Gaussian's sigma in pixels of 0.22 mm: a new intensifier
# resolves 1.4-1.6 line pairs per mm at a 23 cm field (10% MTF: sigma 1.0-1.1 px), a worn
# one or a binned flat panel about 0.8 (2.0 px); the idealised frame's is
# XRayParams.detector_blur_px.
_UNSHARPNESS_PX = (0.7, 2.0)
# Nuisances not yet in the operating-room scene: with the unsharpness in it, the scene's
# pins seen end-on as stubs (seed 8, view 1) and seed 17's view 2 no longer have their pins
# labelled right (docs/realism.md, thirty-second pass).
_NOT_YET_IN_THE_ROOM = ("unsharpness",)

_MU_LEAD_LINE = 6.0  # line integral of a lead letter 1.5 mm thick: opaque
_MU_STEEL = 0.9
_MU_BONE_EXCESS = 0.03  # cortical bone over soft tissue, as XRayParams


@dataclass(frozen=True)
class OperatingRoom:
    """Which nuisances a simulated frame carries (all off: the idealised scene)."""

    femur: bool = False
    patella: bool = False
    retractors: bool = False
    marker: bool = False
    shutters: bool = False
    dose: bool = False
    scatter: bool = False
    flat_panel: bool = False
    processing: bool = False
    text: bool = False
    leg_width: bool = False
    views: bool = False
    headed_pins: bool = False
    unsharpness: bool = False
    mesh_folder: Path | None = None  # femur-generic-right.stl, patella-right.stl (metres)

    @staticmethod
    def everything(mesh_folder: Path | None = None) -> OperatingRoom:
        """The default operating-room scene: every nuisance at once (but those not yet in it)."""
        return OperatingRoom(**{name: True for name in NUISANCES if name not in _NOT_YET_IN_THE_ROOM},
                             mesh_folder=mesh_folder)

    @staticmethod
    def only(name: str, mesh_folder: Path | None = None) -> OperatingRoom:
        return OperatingRoom.of([name], mesh_folder)

    @staticmethod
    def of(names: list[str], mesh_folder: Path | None = None) -> OperatingRoom:
        """The scene with just these nuisances on."""
        unknown = [name for name in names if name not in NUISANCES]
        if unknown:
            raise ValueError(f"unknown nuisance(s) {unknown}; choose from {', '.join(NUISANCES)}")
        return replace(OperatingRoom(mesh_folder=mesh_folder), **{name: True for name in names})

    @property
    def names(self) -> list[str]:
        return [f.name for f in fields(self) if f.name in NUISANCES and getattr(self, f.name)]

    def draw(self, seed: int) -> RoomDraw:
        """The random particulars of one case (its own stream: the case's truth is unchanged)."""
        rng = np.random.default_rng([seed, 26])
        processing = None
        if self.processing:
            processing = {"log": bool(rng.random() < 0.7), "unsharp": float(rng.uniform(0.0, 1.5)),
                          "unsharp_sigma_px": float(rng.uniform(6.0, 30.0)),
                          "gamma": float(rng.uniform(0.6, 1.6)), "window_pct": float(rng.uniform(0.0, 2.0)),
                          "invert": bool(rng.random() < 0.3), "bits": int(rng.choice([8, 10, 12, 16]))}
        return RoomDraw(
            self, flexion_deg=float(rng.uniform(70.0, 110.0)),
            femur_posterior_mm=float(rng.uniform(0.0, 20.0)),
            femur_lift_mm=float(rng.uniform(0.0, 6.0)),
            patella_everted=bool(rng.random() < 0.5), patella_rotation=rng.normal(size=3),
            patella_offset=rng.uniform([35.0, 5.0, -5.0], [60.0, 35.0, 35.0]),
            retractors=[(str(site), float(rng.uniform(15.0, 20.0)), float(rng.uniform(30.0, 70.0)),
                         float(rng.uniform(-25.0, 25.0)))
                        for site in rng.permutation(["medial", "lateral", "posterior"])[:rng.integers(1, 4)]],
            marker_letter=str(rng.choice(["R", "L"])), marker_where=rng.uniform(0.15, 0.85, 2),
            shutters=[(int(side), float(rng.uniform(0.06, 0.2)), float(rng.uniform(-8.0, 8.0)))
                      for side in rng.permutation(4)[:rng.integers(1, 3)]],
            photons=float(np.exp(rng.uniform(np.log(300.0), np.log(4000.0)))),
            scatter_spr=float(rng.uniform(0.3, 1.0)), processing=processing,
            leg_half_width_mm=float(rng.uniform(45.0, 80.0)), view_kind=str(rng.choice(["ap-lateral", "oblique"])),
            view_jitter=rng.uniform(0.0, 1.0, 2), detector_blur_px=float(rng.uniform(*_UNSHARPNESS_PX)))


@dataclass
class RoomDraw:
    """One case's draws of the nuisances its :class:`OperatingRoom` turns on."""

    room: OperatingRoom
    flexion_deg: float
    femur_posterior_mm: float
    femur_lift_mm: float
    patella_everted: bool
    patella_rotation: np.ndarray
    patella_offset: np.ndarray
    retractors: list[tuple[str, float, float, float]]  # site, width, bend (deg), splay (deg)
    marker_letter: str
    marker_where: np.ndarray
    shutters: list[tuple[int, float, float]]  # side (0 left, 1 top, 2 right, 3 bottom), depth, tilt
    photons: float
    scatter_spr: float
    processing: dict | None
    leg_half_width_mm: float
    view_kind: str
    view_jitter: np.ndarray
    detector_blur_px: float

    def params(self, base: XRayParams) -> XRayParams:
        """The renderer's parameters under these draws (dose, detector, leg width, bits)."""
        p = base
        if self.room.dose:
            p = replace(p, photons=self.photons)
        if self.room.unsharpness:
            p = replace(p, detector_blur_px=self.detector_blur_px)
        if self.room.flat_panel:
            p = replace(p, vignetting=0.0)
        if self.room.leg_width:
            scale = self.leg_half_width_mm / 58.0  # the default envelope's half-width at the knee
            p = replace(p, envelope_profile_mm=tuple((z, a * scale, b * (0.5 + 0.5 * scale))
                                                     for z, a, b in p.envelope_profile_mm))
        if self.processing is not None:
            p = replace(p, bits_stored=self.processing["bits"])
        return p

    def camera(self, camera: Camera) -> Camera:
        return replace(camera, fov_radius_px=None) if self.room.flat_panel else camera

    def distortion(self, camera: Camera, default: Distortion) -> Distortion:
        return Distortion.none(camera.width, camera.height) if self.room.flat_panel else default


def view_angles(draw: RoomDraw, default: tuple[float, ...]) -> tuple[float, ...]:
    """The two view angles about the leg axis (0 = AP) a surgeon takes, or ``default``."""
    if not draw.room.views:
        return default
    a, b = draw.view_jitter
    if draw.view_kind == "ap-lateral":
        return (-20.0 + 40.0 * a, (60.0 + 30.0 * b) * (1 if a < 0.5 else -1))
    return (-(30.0 + 20.0 * a), 30.0 + 20.0 * b)


# -- bodies ---------------------------------------------------------------------------------

def _osim_mesh(path: Path, medial_sign: float) -> trimesh.Trimesh:
    """A right-side OpenSim mesh (metres; +x anterior, +y proximal, +z right) in the tibia's
    anatomical axes (mm; +y anterior, +z proximal, +x = y x z, i.e. right), mirrored for a
    left knee (whose lateral side is -x)."""
    mesh = trimesh.load(path, force="mesh")
    v = np.asarray(mesh.vertices, float) * 1000.0
    anat = np.column_stack([v[:, 2], v[:, 0], v[:, 1]])
    faces = np.asarray(mesh.faces)
    if medial_sign > 0:  # medial on +x: a left knee, lateral on -x
        anat[:, 0] *= -1
        faces = faces[:, ::-1]
    out = trimesh.Trimesh(anat, faces, process=True)
    if out.volume < 0:
        out.invert()
    return out


def _parametric_femur() -> trimesh.Trimesh:
    """Shaft and two condyles, distal end at z = 0 (anatomical axes, mm)."""
    shaft = trimesh.creation.cylinder(radius=14.0, height=200.0, sections=48)
    shaft.apply_translation([0.0, 0.0, 125.0])
    parts = [shaft]
    for x in (-20.0, 20.0):
        condyle = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        condyle.apply_scale([17.0, 26.0, 22.0])
        condyle.apply_translation([x, -4.0, 22.0])
        parts.append(condyle)
    return trimesh.boolean.union(parts, engine="manifold")


_FEMUR_KEPT_MM = 160.0  # of the femur's distal end: the rest is outside every knee frame


def _femur(draw: RoomDraw, medial_sign: float) -> trimesh.Trimesh:
    """The distal femur at the draw's flexion, in the anatomical frame: condyles resting on
    the plateau (z = 0) in extension, then turned about the posterior condyles' centre
    (about 20 mm above the plateau, 12 mm behind the knee centre) so that flexion swings the
    shaft backwards (-y), and moved back onto or behind the plateau."""
    folder = draw.room.mesh_folder
    path = None if folder is None else Path(folder) / "femur-generic-right.stl"
    if path is not None and path.is_file():
        femur = _osim_mesh(path, medial_sign)
        low = femur.vertices[:, 2].min()
        distal = femur.vertices[femur.vertices[:, 2] < low + 30.0]
        centre = 0.5 * (distal.min(axis=0) + distal.max(axis=0))
        femur.apply_translation([-centre[0], -centre[1], -low])
        box = trimesh.creation.box([300.0, 300.0, _FEMUR_KEPT_MM])
        box.apply_translation([0.0, 0.0, _FEMUR_KEPT_MM / 2.0 - 1.0])
        femur = trimesh.boolean.intersection([femur, box], engine="manifold")
    else:
        femur = _parametric_femur()
    femur.apply_translation([0.0, 0.0, 1.5 + draw.femur_lift_mm])  # cartilage between
    hinge = np.array([0.0, -12.0, 20.0])
    R = rotation_about([1.0, 0.0, 0.0], np.radians(draw.flexion_deg))  # +z turns towards -y
    v = (femur.vertices - hinge) @ R.T + hinge
    v[:, 1] -= draw.femur_posterior_mm
    return trimesh.Trimesh(v, femur.faces, process=False)


def _patella(draw: RoomDraw, medial_sign: float) -> trimesh.Trimesh | None:
    folder = draw.room.mesh_folder
    path = None if folder is None else Path(folder) / "patella-right.stl"
    if path is None or not path.is_file():
        return None
    patella = _osim_mesh(path, medial_sign)
    patella.apply_translation(-patella.vertices.mean(axis=0))
    turn = np.pi if draw.patella_everted else 0.3
    R = rotation_about(draw.patella_rotation, turn) @ rotation_about([0.0, 0.0, 1.0], np.pi / 2 * draw.patella_everted)
    lateral = -medial_sign
    offset = draw.patella_offset * np.array([lateral, 1.0, 1.0])
    return trimesh.Trimesh(patella.vertices @ R.T + offset, patella.faces, process=False)


def _retractor(site: str, width: float, bend_deg: float, splay_deg: float, medial_sign: float
               ) -> trimesh.Trimesh:
    """A bent blade (2 mm steel) hooked over the plateau rim at ``site``: a 35 mm tip down
    along the bone, then the rest (115 mm) bent outwards by ``bend_deg``."""
    tip = trimesh.creation.box([2.0, width, 35.0])
    tip.apply_translation([0.0, 0.0, -17.5])
    handle = trimesh.creation.box([2.0, width, 115.0])
    handle.apply_translation([0.0, 0.0, 57.5])
    handle.apply_transform(_homogeneous(rotation_about([0.0, 1.0, 0.0], np.radians(bend_deg))))
    blade = trimesh.boolean.union([tip, handle], engine="manifold")
    # Local +x points away from the bone; place it at the rim of its site.
    outward = {"medial": np.array([medial_sign, 0.0, 0.0]), "lateral": np.array([-medial_sign, 0.0, 0.0]),
               "posterior": np.array([0.0, -1.0, 0.0])}[site]
    rim = {"medial": 40.0, "lateral": 40.0, "posterior": 30.0}[site]
    yaw = np.arctan2(outward[1], outward[0]) + np.radians(splay_deg)
    R = rotation_about([0.0, 0.0, 1.0], yaw)
    v = blade.vertices @ R.T + (rim + 1.5) * outward + np.array([0.0, 0.0, 5.0])
    return trimesh.Trimesh(v, blade.faces, process=False)


def _homogeneous(R: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = R
    return M


def room_bodies(plan: Plan, draw: RoomDraw) -> list[tuple[str, Body]]:
    """The draw's foreign bodies in the anatomical frame, named (femur, patella, retractor)."""
    medial = plan.landmarks.medial_sign
    bodies = []
    if draw.room.femur:
        femur = _femur(draw, medial)
        bodies.append(("femur", Body(femur.vertices, femur.faces, _MU_BONE_EXCESS)))
    if draw.room.patella:
        patella = _patella(draw, medial)
        if patella is not None:
            bodies.append(("patella", Body(patella.vertices, patella.faces, _MU_BONE_EXCESS)))
    if draw.room.retractors:
        for site, width, bend, splay in draw.retractors:
            blade = _retractor(site, width, bend, splay, medial)
            bodies.append(("retractor", Body(blade.vertices, blade.faces, _MU_STEEL - 0.02)))
    return bodies


def pin_heads(plan: Plan) -> Body:
    """A head on the pin's driven end (6 mm across, 8 mm long; pin frame, tip at z = 0)."""
    head = trimesh.creation.cylinder(radius=3.0, height=8.0, sections=32)
    head.apply_translation([0.0, 0.0, plan.pin_length() - 4.0])
    return Body(head.vertices, head.faces, _MU_STEEL - 0.02)


# -- the detector and the C-arm's processing -------------------------------------------------

def _shutter_mask(draw: RoomDraw, shape: tuple[int, int], origin: np.ndarray, size: int) -> np.ndarray:
    """Canvas pixels behind the collimator blades (True); ``size``: the frame's side, px."""
    height, width = shape
    u, v = np.meshgrid(np.arange(width) + origin[0], np.arange(height) + origin[1])
    mask = np.zeros(shape, bool)
    for side, depth, tilt in draw.shutters:
        slope = np.tan(np.radians(tilt))
        across, along = (u, v) if side in (0, 2) else (v, u)
        edge = depth * size + slope * (along - size / 2)
        mask |= across < edge if side in (0, 1) else across > size - edge
    return mask


def _marker_mask(draw: RoomDraw, width: int, height: int) -> np.ndarray:
    """A lead letter about 60 px tall, lying on the detector."""
    canvas = np.zeros((height, width), np.uint8)
    x, y = (draw.marker_where * [width, height]).astype(int)
    cv2.putText(canvas, draw.marker_letter, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 2.2, 255, 9)
    return canvas > 0


def _process(detected: np.ndarray, lit: np.ndarray, spec: dict) -> np.ndarray:
    """The C-arm's processing of detected quanta into stored grey levels (``bits``)."""
    y = np.log(np.maximum(detected, 1.0)) if spec["log"] else detected.astype(np.float64)
    if spec["unsharp"] > 0:
        y = y + spec["unsharp"] * (y - cv2.GaussianBlur(y, (0, 0), spec["unsharp_sigma_px"]))
    lo, hi = np.percentile(y[lit], [spec["window_pct"], 100.0 - spec["window_pct"]])
    y = np.clip((y - lo) / max(hi - lo, 1e-9), 0.0, 1.0) ** spec["gamma"]
    top = (1 << spec["bits"]) - 1
    grey = np.round(y * top)
    grey = np.where(lit, grey, 0.0)
    if spec["invert"]:
        grey = top - grey
    return grey.astype(np.uint16)


def _burn_text(image: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """Patient and exposure annotations in the corners, at the brightest grey level."""
    top = (1 << bits) - 1
    h, w = image.shape
    mask = np.zeros((h, w), np.uint8)
    lines = [("SMITH^JOHN  ID 00417", (12, 28)), (f"{rng.integers(60, 80)} kV {rng.uniform(1, 4):.1f} mA", (12, h - 16)),
             ("R  KNEE  AP", (w - 200, 28)), (f"{rng.integers(1, 28):02d}.11.2026 10:{rng.integers(10, 59)}", (w - 260, h - 16))]
    for text, at in lines:
        cv2.putText(mask, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 2)
    return np.where(mask > 0, top, image).astype(image.dtype)


def expose_room(line_integral: np.ndarray, origin: np.ndarray, camera: Camera, params: XRayParams,
                distortion: Distortion, draw: RoomDraw, rng: np.random.Generator) -> np.ndarray:
    """Detector image of a canvas line integral under the draw: shutters, lead marker,
    scatter, quantum noise, the detector (intensifier or flat panel), then the C-arm's
    processing and burned-in text."""
    height, width = line_integral.shape
    total = line_integral.astype(np.float64)
    if draw.room.shutters:
        total = total + 3.0 * _shutter_mask(draw, total.shape, origin, camera.width)  # lead blades: ~5% through
    if draw.room.marker:
        total = total + _MU_LEAD_LINE * _marker_mask(draw, width, height)
    primary = params.photons * np.exp(-total)
    expected = _blur(primary, params.focal_blur_px)
    if draw.room.scatter:
        low = cv2.GaussianBlur(primary.astype(np.float32), (0, 0), 60.0).astype(np.float64)
        expected = expected + draw.scatter_spr * low
    counts = rng.poisson(expected).astype(np.float32)
    image = _blur(distortion.warp(counts, camera.width, camera.height, tuple(origin)),
                  params.detector_blur_px)
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    r = np.hypot(u - distortion.centre_u, v - distortion.centre_v)
    image = image * (1.0 - params.vignetting * (r / distortion.radius) ** 2)
    fov = camera.fov_radius_px or np.inf
    aperture = np.clip(fov - r + 0.5, 0.0, 1.0)
    lit = aperture > 0.5
    if draw.processing is not None:
        stored = _process(image * aperture, lit, draw.processing)
        bits = draw.processing["bits"]
    else:
        full_scale = (1 << params.bits_stored) - 1
        grey = params.dark_level + image * (0.85 * full_scale - params.dark_level) / params.photons
        grey = params.dark_level + (grey - params.dark_level) * aperture
        if params.invert:
            grey = full_scale - grey
        stored = np.clip(np.round(grey), 0, full_scale).astype(np.uint16)
        bits = params.bits_stored
    if draw.room.text:
        stored = _burn_text(stored, bits, rng)
    return stored


# -- a frame and its truth -------------------------------------------------------------------

_HIDDEN_LINE_INTEGRAL = 0.5  # foreign attenuation over a true outline point that hides it


@dataclass
class RoomFrame:
    """A rendered operating-room frame; ``hidden`` flags, per label, the true outline points
    (of ``radiograph.silhouettes``) lying behind a foreign body, a shutter or the marker."""

    radiograph: Radiograph
    hidden: dict[str, np.ndarray]
    foreign: list[str]


def room_scene(scene: XRayScene, draw: RoomDraw) -> XRayScene:
    """``scene`` with the draw's soft-tissue envelope (the leg's width)."""
    if not draw.room.leg_width:
        return scene
    envelope = _envelope(draw.params(scene.params))
    return replace(scene, anatomy=[Body(envelope.vertices, envelope.faces, scene.params.mu_soft_per_mm,
                                        smooth=True)] + scene.anatomy[1:])


def render_room(plan: Plan, T_cam_tibia: Pose, T_tibia_pins: tuple[Pose, ...] | list[Pose],
                camera: Camera, params: XRayParams, draw: RoomDraw, rng: np.random.Generator,
                scene: XRayScene, bodies: list[tuple[str, Body]]) -> RoomFrame:
    """One frame of the case under ``draw``; ``scene`` from :func:`room_scene`, ``bodies``
    from :func:`room_bodies` (both built once per case)."""
    cam = draw.camera(camera)
    distortion = draw.distortion(cam, params.distortion or default_distortion(camera))
    params = replace(draw.params(params), distortion=distortion)
    T_cam_anat = T_cam_tibia @ scene.T_tibia_anat
    extra = [(body, T_cam_anat) for _, body in bodies]
    if draw.room.headed_pins:
        head = pin_heads(plan)
        extra += [(head, T_cam_tibia @ T) for T in T_tibia_pins]

    def exposure(line_integral, origin, c, p, d, r):
        return expose_room(line_integral, origin, c, p, d, draw, r)

    radiograph = render_radiograph(plan, T_cam_tibia, T_tibia_pins, cam, params, rng, scene, extra,
                                   exposure)
    origin, width, height = _canvas(cam, distortion)
    foreign = (render_bodies(extra, cam, origin, width, height) if extra
               else np.zeros((height, width), np.float32)).astype(np.float64)
    if draw.room.shutters:
        foreign += 3.0 * _shutter_mask(draw, foreign.shape, origin, cam.width)
    if draw.room.marker:
        foreign += _MU_LEAD_LINE * _marker_mask(draw, width, height)
    hidden = {}
    for label, points in radiograph.silhouettes.items():
        if len(points) == 0:
            hidden[label] = np.zeros(0, bool)
            continue
        at = np.round(distortion.undistort(points) - origin).astype(int)
        at = np.clip(at, 0, [width - 1, height - 1])
        hidden[label] = foreign[at[:, 1], at[:, 0]] > _HIDDEN_LINE_INTEGRAL
    names = [name for name, _ in bodies] + (["pin heads"] if draw.room.headed_pins else [])
    return RoomFrame(radiograph, hidden, names)
