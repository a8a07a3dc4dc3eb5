"""The pre-operative plan and the rigid models built from it.

A plan (one per patient and side) holds the tibia surface (with the fibula), its landmarks,
the pin model and the planned resection angles with their tolerance. Everything derived from
it that is expensive (signed distance fields) is computed once and cached beside the plan,
never during surgery.

Plan folder::

    plan.json        format, patient, side, mesh files with units, landmarks, pin, target,
                     the bone's segmentation error (SD, mm)
    tibia.stl ...    meshes named in plan.json
    cache/           the meshes' processed arrays, signed distance fields and silhouette
                     topology, keyed by what they derive from (safe to delete:
                     solver.plan_cache); written when the plan is added, so that loading
                     a plan for a solve reads arrays and never needs trimesh
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from slamtka.solver.anatomy import Landmarks
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.plan_cache import cache_key, read_arrays, write_arrays
from slamtka.solver.sdf import SignedDistanceField
from slamtka.solver.silhouette import ContourGenerator, simplified
from slamtka.solver.surface import Surface, mesh_digest

__all__ = ["Plan", "Target", "RigidModel", "PLAN_FORMAT", "check_layout"]

log = logging.getLogger(__name__)

PLAN_FORMAT = "slamtka-plan/1"
BONE_EXTENT_MM = (40.0, 600.0)
PIN_EXTENT_MM = (20.0, 300.0)
# Silhouettes are traced on a simplified copy of a large mesh: the outline moves by far less
# than a pixel, and the cost per iteration stays low.
_SILHOUETTE_MAX_FACES = 6000
_SEARCH_MAX_FACES = 1500
# Bump when the stored surfaces or silhouette topology change meaning.
_STORE_VERSION = 1
# Segmentation error of a bone surface from CT (SD, mm), when the plan does not state its own.
DEFAULT_SEGMENTATION_SD_MM = 0.5
# A fibula lies beside its tibia and the knee centre on the tibia's plateau, so their bounding
# boxes touch or overlap. Farther apart than this they belong to another patient, frame or unit
# (and a distance field spanning both would be enormous).
MAX_LAYOUT_GAP_MM = 50.0


@dataclass(frozen=True)
class Target:
    """Planned resection angles and the tolerance on each (degrees)."""

    ctr_deg: float = 0.0
    str_deg: float = 3.0
    tolerance_deg: float = 3.0

    def __post_init__(self) -> None:
        for name in ("ctr_deg", "str_deg", "tolerance_deg"):
            value = getattr(self, name)
            # NaN passes every range comparison below, so finiteness is checked first.
            if (isinstance(value, bool) or not isinstance(value, numbers.Real)
                    or not math.isfinite(value)):
                raise ValueError(f"target {name} must be a finite number of degrees, got {value!r}")
        if not 0.0 < self.tolerance_deg <= 15.0:
            raise ValueError(f"tolerance {self.tolerance_deg} deg is outside (0, 15]")
        if abs(self.ctr_deg) > 20.0 or abs(self.str_deg) > 20.0:
            raise ValueError("planned CTR/STR beyond 20 deg are not plausible")


def _box_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (mm) between two axis-aligned boxes given as (2, 3) lower/upper corners."""
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(a[0] - b[1], b[0] - a[1]))))


def check_layout(tibia: Surface, fibula: Surface | None, landmarks: Landmarks,
                 fibula_name: str = "fibula", landmarks_name: str = "landmarks") -> None:
    """Refuse a fibula or landmarks that cannot belong to this tibia (another patient, frame
    or units): caught at import, with the file named, rather than as a wrong measurement or
    an enormous distance field. The names are those of the files, for the message."""
    if fibula is not None:
        gap = _box_gap(fibula.bounds, tibia.bounds)
        if gap > MAX_LAYOUT_GAP_MM:
            raise ValueError(
                f"{fibula_name}: the fibula lies {gap:.0f} mm away from the tibia (more than "
                f"{MAX_LAYOUT_GAP_MM:.0f} mm between their bounding boxes): not this tibia's "
                "fibula, or in another frame or units")
    knee = landmarks.knee_centre
    gap = _box_gap(np.vstack([knee, knee]), tibia.bounds)
    if gap > MAX_LAYOUT_GAP_MM:
        raise ValueError(
            f"{landmarks_name}: the knee centre {np.round(knee, 1).tolist()} mm lies {gap:.0f} mm "
            f"outside the tibia mesh's bounding box (more than {MAX_LAYOUT_GAP_MM:.0f} mm): "
            "landmarks of another mesh, frame or units")


def _read_surface(path: Path, extent_mm: tuple[float, float], units: str = "auto",
                  require_watertight: bool = False, cache_dir: Path | None = None) -> Surface:
    """A mesh file's surface in mm, checked (:func:`slamtka.solver.meshes.load_mesh`): read
    from ``cache_dir`` when the file was read before (the entry is named by the file's
    bytes), else read with trimesh and stored there."""
    stored = None
    if cache_dir is not None and path.is_file():
        key = cache_key(hashlib.sha256(path.read_bytes()).hexdigest(), units, extent_mm,
                        require_watertight, _STORE_VERSION)
        stored = Path(cache_dir) / f"surface-{key}.npz"
        arrays = read_arrays(stored, "mesh")
        if arrays is not None:
            return Surface(arrays["vertices"], arrays["faces"])
    from slamtka.solver.meshes import load_mesh  # needs trimesh (~1 s to import): files not read before

    surface = Surface.of(load_mesh(path, extent_mm, units, require_watertight))
    if stored is not None:
        log.info("%s: read with trimesh; its arrays are stored in %s", path, stored.parent)
        write_arrays(stored, vertices=surface.vertices, faces=surface.faces)
    return surface


def _union(meshes: Sequence[Surface]) -> Surface:
    """One surface of all ``meshes`` (their faces re-indexed into the joined vertices)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Surface(np.vstack([m.vertices for m in meshes]),
                   np.vstack([m.faces + o for m, o in zip(meshes, offsets)]))


def _silhouettes(meshes: Sequence[Surface], cache_dir: Path | None
                 ) -> tuple[ContourGenerator, ContourGenerator]:
    """The silhouette topology of the meshes' union, simplified for the iterations and
    further for the global set-up search: read from ``cache_dir``, else built (decimating
    and finding each edge's faces needs trimesh and ~0.1 s per model) and stored there."""
    path = None
    if cache_dir is not None:
        key = cache_key(mesh_digest(meshes), _SILHOUETTE_MAX_FACES, _SEARCH_MAX_FACES, _STORE_VERSION)
        path = Path(cache_dir) / f"silhouettes-{key}.npz"
        arrays = read_arrays(path, "silhouette topology")
        if arrays is not None:
            return ContourGenerator.from_arrays(arrays, "fine_"), ContourGenerator.from_arrays(arrays, "coarse_")
    fine = simplified(_union(meshes).to_trimesh(), _SILHOUETTE_MAX_FACES)
    coarse = simplified(fine, _SEARCH_MAX_FACES)
    contour, coarse_contour = ContourGenerator.from_mesh(fine), ContourGenerator.from_mesh(coarse)
    if path is not None:
        write_arrays(path, **contour.arrays("fine_"), **coarse_contour.arrays("coarse_"))
    return contour, coarse_contour


@dataclass
class RigidModel:
    """A rigid body as the solver sees it: signed distance field and silhouette topology."""

    name: str
    meshes: list[Surface]
    sdf: SignedDistanceField
    contour: ContourGenerator
    coarse_contour: ContourGenerator  # a lighter mesh for the global set-up search

    @staticmethod
    def build(
        name: str,
        meshes: list[Surface],
        sdf_spacing_mm: float,
        cache_dir: Path | None,
    ) -> RigidModel:
        margin = 8.0 * sdf_spacing_mm
        sdf = SignedDistanceField.cached(meshes, sdf_spacing_mm, margin, cache_dir)
        return RigidModel(name, meshes, sdf, *_silhouettes(meshes, cache_dir))


class PinShadows(NamedTuple):
    """Where a plan's pins show in a view at a pose: their centres' pixels (2, 2), and the
    width and length (px) of one pin's shadow, which tell pins from other straight metal."""

    centres: np.ndarray
    width_px: float
    length_px: float


@dataclass
class Plan:
    """Everything known before surgery about one patient's tibia and the pins."""

    tibia: Surface
    fibula: Surface | None
    landmarks: Landmarks
    pin_mesh: Surface
    pin_spec: PinSpec | None  # None when a custom pin mesh replaces the parametric pin
    target: Target = field(default_factory=Target)
    patient_id: str = "ANON"
    folder: Path | None = None
    # SD of the bone surface's segmentation error (mm): smooth over the bone, it biases the
    # views alike, so the solver adds it to the uncertainty as an error shared by nearby
    # edge points. A mesh from CT carries about DEFAULT_SEGMENTATION_SD_MM; the built-in
    # phantom is exact.
    segmentation_sd_mm: float = DEFAULT_SEGMENTATION_SD_MM
    _models: dict[str, RigidModel] = field(default_factory=dict, repr=False)

    @property
    def side(self) -> str:
        return self.landmarks.side

    @property
    def cache_dir(self) -> Path:
        """Beside the plan; plans not yet saved share the user's cache (keyed by mesh hash)."""
        if self.folder is not None:
            return self.folder / "cache"
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        return Path(base) / "slamtka"

    @staticmethod
    def from_meshes(tibia: Path, fibula: Path | None, landmarks: Path,
                    target: Target = Target(),
                    segmentation_sd_mm: float = DEFAULT_SEGMENTATION_SD_MM) -> Plan:
        """A plan from mesh files (units detected) and a landmarks JSON, default pin."""
        spec = PinSpec()
        tibia_mesh = _read_surface(tibia, BONE_EXTENT_MM)
        fibula_mesh = None if fibula is None else _read_surface(fibula, BONE_EXTENT_MM)
        marks = Landmarks.load(landmarks)
        check_layout(tibia_mesh, fibula_mesh, marks, str(fibula), str(landmarks))
        return Plan(tibia_mesh, fibula_mesh, marks, build_pin(spec), spec, target,
                    segmentation_sd_mm=segmentation_sd_mm)

    def bone_meshes(self) -> list[Surface]:
        return [self.tibia] if self.fibula is None else [self.tibia, self.fibula]

    def bone_model(self) -> RigidModel:
        """Tibia (with fibula) model; its signed distance field is cached beside the plan."""
        if "bone" not in self._models:
            self._models["bone"] = RigidModel.build("bone", self.bone_meshes(), 1.0, self.cache_dir)
        return self._models["bone"]

    def pin_model(self) -> RigidModel:
        if "pin" not in self._models:
            self._models["pin"] = RigidModel.build("pin", [self.pin_mesh], 0.2, self.cache_dir)
        return self._models["pin"]

    def pin_length(self) -> float:
        """Extent of the pin along its axis (pin frame +z), mm."""
        return float(self.pin_mesh.bounds[1, 2] - self.pin_mesh.bounds[0, 2])

    def pin_diameter(self) -> float:
        """The pin's shaft diameter, mm (of a custom mesh: its typical distance from the axis)."""
        if self.pin_spec is not None:
            return self.pin_spec.diameter_mm
        radial = np.hypot(self.pin_mesh.vertices[:, 0], self.pin_mesh.vertices[:, 1])
        return 2.0 * float(np.percentile(radial, 75))

    def pin_shadows(self, camera: Camera, T_cam_tibia: Pose, T_tibia_pins: Sequence[Pose]
                    ) -> PinShadows:
        """Where the pins at ``T_tibia_pins`` show in a view (ideal, undistorted pixels)."""
        lo, hi = self.pin_mesh.bounds[:, 2]
        axis = np.array([[0.0, 0.0, 0.5 * self.pin_length()], [0.0, 0.0, lo], [0.0, 0.0, hi]])
        points = np.array([(T_cam_tibia @ T).apply(axis) for T in T_tibia_pins])  # (pins, 3, 3)
        width = camera.fx * self.pin_diameter() / float(np.mean(points[:, 0, 2]))
        ends = camera.project(points[:, 1:].reshape(-1, 3)).reshape(-1, 2, 2)
        length = float(np.mean(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)))
        return PinShadows(camera.project(points[:, 0]), width, length)

    # -- persistence ---------------------------------------------------------------------
    def save(self, folder: Path) -> None:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.tibia.to_trimesh().export(folder / "tibia.stl")
        doc: dict = {
            "format": PLAN_FORMAT,
            "patient_id": self.patient_id,
            "side": self.side,
            "tibia": {"file": "tibia.stl", "units": "mm"},
            "fibula": None,
            "landmarks": self.landmarks.to_json(),
            "segmentation_sd_mm": self.segmentation_sd_mm,
            "target": {
                "ctr_deg": self.target.ctr_deg,
                "str_deg": self.target.str_deg,
                "tolerance_deg": self.target.tolerance_deg,
            },
        }
        if self.fibula is not None:
            self.fibula.to_trimesh().export(folder / "fibula.stl")
            doc["fibula"] = {"file": "fibula.stl", "units": "mm"}
        if self.pin_spec is not None:
            doc["pin"] = {"parametric": self.pin_spec.__dict__}
        else:
            self.pin_mesh.to_trimesh().export(folder / "pin.stl")
            doc["pin"] = {"file": "pin.stl", "units": "mm"}
        (folder / "plan.json").write_text(json.dumps(doc, indent=2))
        self.folder = folder

    @staticmethod
    def load(folder: Path) -> Plan:
        folder = Path(folder)
        path = folder / "plan.json"
        if not path.is_file():
            raise ValueError(f"{folder}: no plan.json (not a plan folder)")
        doc = read_json_object(path)
        if doc.get("format") != PLAN_FORMAT:
            raise ValueError(f"{path}: format {doc.get('format')!r} is not {PLAN_FORMAT!r}")
        try:
            cache = folder / "cache"
            tibia = _read_surface(folder / doc["tibia"]["file"], BONE_EXTENT_MM,
                                  doc["tibia"].get("units", "auto"), cache_dir=cache)
            fibula = None
            if doc.get("fibula"):
                fibula = _read_surface(folder / doc["fibula"]["file"], BONE_EXTENT_MM,
                                       doc["fibula"].get("units", "auto"), cache_dir=cache)
            landmarks = Landmarks.from_json(doc["landmarks"])
            if landmarks.side != doc["side"]:
                raise ValueError(f"{path}: plan side {doc['side']!r} differs from landmarks")
            pin_doc = doc.get("pin", {"parametric": {}})
            if "file" in pin_doc:
                pin_spec = None
                pin_mesh = _read_surface(folder / pin_doc["file"], PIN_EXTENT_MM,
                                         pin_doc.get("units", "auto"), require_watertight=True,
                                         cache_dir=cache)
            else:
                pin_spec = PinSpec(**pin_doc.get("parametric", {}))
                pin_mesh = build_pin(pin_spec)
            try:
                target = Target(**doc.get("target", {}))
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from None
            segmentation_sd_mm = doc.get("segmentation_sd_mm", DEFAULT_SEGMENTATION_SD_MM)
            if (isinstance(segmentation_sd_mm, bool) or not isinstance(segmentation_sd_mm, (int, float))
                    or not 0.0 <= segmentation_sd_mm <= 5.0):
                raise ValueError(f"{path}: segmentation_sd_mm must be a number of mm in [0, 5], "
                                 f"got {segmentation_sd_mm!r}")
        except KeyError as missing:
            raise ValueError(f"{path}: missing field {missing}") from None
        except TypeError as exc:
            raise ValueError(f"{path}: malformed field ({exc})") from None
        return Plan(tibia, fibula, landmarks, pin_mesh, pin_spec, target,
                    str(doc.get("patient_id", "ANON")), folder, segmentation_sd_mm)
