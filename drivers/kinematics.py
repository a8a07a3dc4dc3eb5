"""C-arm kinematics: encoder joint values to the X-ray source and detector pose, and from a
nominal patient set-up to each view's initial pose ``T_cam_tibia``.

Frame ``carm`` (the C-arm's base frame, README.md, Conventions): origin at the isocentre with
every joint at zero, +z vertically up, +x horizontal along the L-arm from the column towards
the C (across the table), +y = z x x (along the table). With every joint at zero the source
is below the table at ``(0, 0, -source_to_isocentre)`` and the camera frame ``cam`` has the
axes of ``carm``: +z from the source up towards the detector, image columns along +x, rows
along +y.

The chain is configurable: an ordered list of joints from the base to the C, each revolute
(degrees, about a direction through a pivot) or prismatic (millimetres, along a direction),
written in the frame left by the joints before it. The default is a mobile C-arm: lift (up),
wig-wag (about the vertical through the column, 750 mm behind the isocentre), horizontal
travel (along the arm), angulation (about the arm, through the isocentre) and orbital
rotation (about the C's own axis, through the isocentre). Signs follow DICOM for a supine
patient whose head points to -y: positive orbital moves the detector towards the patient's
left (LAO), positive angulation towards the head (cranial). The source-to-detector distance
(SID) moves only the detector; the source stays ``source_to_isocentre_mm`` from the
isocentre.

Units: joint values in degrees and millimetres (as the encoders report them), poses in mm.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from slamtka.drivers.config_tables import check_keys, config_number
from slamtka.solver.anatomy import Landmarks
from slamtka.solver.geometry import Pose, rotation_about, so3_log

__all__ = [
    "AXIS_UNITS", "JointReading", "ChainJoint", "CArmKinematics", "PatientSetup", "RelativePose",
    "initial_view_poses", "dicom_angles", "AngleCheck", "check_dicom_angles",
]

# The axes a C-arm reports and their units; "sid" is optional (many C-arms have a fixed SID).
AXIS_UNITS = {"orbital": "deg", "angulation": "deg", "wigwag": "deg", "lift": "mm",
              "travel": "mm", "sid": "mm"}
CHAIN_AXES = ("orbital", "angulation", "wigwag", "lift", "travel")
JOINT_FIELD = {axis: f"{axis}_{unit}" for axis, unit in AXIS_UNITS.items()}  # JointReading field
_JOINT_FIELDS = tuple(JOINT_FIELD.values())


@dataclass(frozen=True)
class JointReading:
    """The joint values of one C-arm position, in degrees and millimetres."""

    orbital_deg: float = 0.0
    angulation_deg: float = 0.0
    wigwag_deg: float = 0.0
    lift_mm: float = 0.0
    travel_mm: float = 0.0
    sid_mm: float | None = None  # None: the C-arm's nominal SID

    def __post_init__(self) -> None:
        for name in _JOINT_FIELDS:
            value = getattr(self, name)
            if value is None and name == "sid_mm":
                continue
            try:
                finite = math.isfinite(value)
            except TypeError:
                finite = False
            if not finite:
                raise ValueError(f"joint value {name} = {value!r} is not a finite number")
            object.__setattr__(self, name, float(value))

    def value(self, axis: str) -> float | None:
        return getattr(self, JOINT_FIELD[axis])

    def chain_value(self, axis: str) -> float:
        """The value of a chain joint (one of CHAIN_AXES), which, unlike the SID, is always set."""
        if axis not in CHAIN_AXES:
            raise ValueError(f"{axis!r} is not a chain axis; chain axes: {CHAIN_AXES}")
        return float(getattr(self, JOINT_FIELD[axis]))

    def axes(self) -> dict[str, float]:
        """Axis name to value, leaving out an unset SID."""
        return {a: v for a in AXIS_UNITS if (v := self.value(a)) is not None}

    @staticmethod
    def from_axes(values: Mapping[str, float]) -> JointReading:
        unknown = set(values) - set(AXIS_UNITS)
        if unknown:
            raise ValueError(f"unknown C-arm axes {sorted(unknown)}; known: {list(AXIS_UNITS)}")
        return JointReading(**{JOINT_FIELD[a]: v for a, v in values.items()})

    def to_json(self) -> dict:
        return {"units": {a: AXIS_UNITS[a] for a in AXIS_UNITS}, **self.axes()}


def _vector(value: Sequence[float], what: str, unit: bool = False) -> np.ndarray:
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{what} must be three finite numbers, got {value!r}")
    if unit:
        norm = np.linalg.norm(v)
        if norm < 1e-9:
            raise ValueError(f"{what} must not be the zero vector")
        v = v / norm
    return v


def _limits(value: Sequence[float], what: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be two numbers [min, max], got {value!r}") from None
    if not lo < hi:
        raise ValueError(f"{what} [{lo}, {hi}] is empty")
    return lo, hi


@dataclass(frozen=True)
class ChainJoint:
    """One joint of the chain: revolute for an angle axis, prismatic for a length axis."""

    axis: str  # which joint value drives it (one of CHAIN_AXES)
    direction: tuple[float, float, float]  # unit vector in the parent frame
    limits: tuple[float, float]  # deg or mm
    sd: float  # 1-sigma uncertainty of the value (encoder plus mechanical play), deg or mm
    pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # a point on a revolute axis

    def __post_init__(self) -> None:
        if self.axis not in CHAIN_AXES:
            raise ValueError(f"chain joint axis {self.axis!r} is not one of {CHAIN_AXES}")
        object.__setattr__(self, "direction", tuple(_vector(self.direction, f"{self.axis} direction", True)))
        object.__setattr__(self, "pivot_mm", tuple(_vector(self.pivot_mm, f"{self.axis} pivot_mm")))
        object.__setattr__(self, "limits", _limits(self.limits, f"{self.axis} limits"))
        if not (np.isfinite(self.sd) and self.sd >= 0):
            raise ValueError(f"{self.axis} sd must be a non-negative number, got {self.sd!r}")

    @property
    def revolute(self) -> bool:
        return AXIS_UNITS[self.axis] == "deg"

    def transform(self, value: float) -> Pose:
        """Motion of this joint at ``value`` (deg or mm), in its parent frame."""
        d = np.asarray(self.direction)
        if not self.revolute:
            return Pose(np.eye(3), d * value)
        R = rotation_about(d, np.radians(value))
        p = np.asarray(self.pivot_mm)
        return Pose(R, p - R @ p)

    def to_config(self) -> dict:
        return {"axis": self.axis, "direction": list(self.direction), "pivot_mm": list(self.pivot_mm),
                "limits": list(self.limits), "sd": self.sd}

    @staticmethod
    def from_config(d: Mapping) -> ChainJoint:
        check_keys(d, {"axis", "direction", "pivot_mm", "limits", "sd"}, "chain joint")
        try:
            return ChainJoint(d["axis"], d["direction"], d["limits"], float(d["sd"]),
                              d.get("pivot_mm", (0.0, 0.0, 0.0)))
        except KeyError as missing:
            raise ValueError(f"chain joint {d.get('axis', '?')!r} lacks {missing}") from None


def _mobile_carm_chain() -> tuple[ChainJoint, ...]:
    return (
        ChainJoint("lift", (0, 0, 1), (0.0, 450.0), 1.0),
        ChainJoint("wigwag", (0, 0, 1), (-12.5, 12.5), 0.2, (-750.0, 0.0, 0.0)),
        ChainJoint("travel", (1, 0, 0), (0.0, 200.0), 1.0),
        ChainJoint("angulation", (1, 0, 0), (-190.0, 190.0), 0.2),
        ChainJoint("orbital", (0, -1, 0), (-95.0, 95.0), 0.2),
    )


@dataclass(frozen=True)
class CArmKinematics:
    """A C-arm's kinematic model; its parameters live in the C-arm's configuration."""

    chain: tuple[ChainJoint, ...] = field(default_factory=_mobile_carm_chain)
    source_to_isocentre_mm: float = 620.0
    sid_nominal_mm: float = 1000.0
    sid_limits_mm: tuple[float, float] = (900.0, 1200.0)
    sid_sd_mm: float = 2.0
    detector_roll_deg: float = 0.0  # image rotation about the beam axis (detector mounting)
    name: str = "generic mobile C-arm"

    def __post_init__(self) -> None:
        axes = [j.axis for j in self.chain]
        if len(set(axes)) != len(axes):
            raise ValueError(f"the chain drives an axis twice: {axes}")
        object.__setattr__(self, "sid_limits_mm", _limits(self.sid_limits_mm, "sid_limits_mm"))
        if not 0 < self.source_to_isocentre_mm < self.sid_limits_mm[0]:
            raise ValueError("the isocentre must lie between the source and the detector "
                             f"(source_to_isocentre_mm {self.source_to_isocentre_mm}, "
                             f"SID limits {self.sid_limits_mm})")
        if not self.sid_limits_mm[0] <= self.sid_nominal_mm <= self.sid_limits_mm[1]:
            raise ValueError(f"nominal SID {self.sid_nominal_mm} mm is outside {self.sid_limits_mm}")
        if not self.sid_sd_mm >= 0:
            raise ValueError("sid_sd_mm must be non-negative")

    # -- joints -----------------------------------------------------------------------------
    def check(self, joints: JointReading) -> None:
        """Raise ValueError naming the first joint value outside its limits."""
        for j in self.chain:
            value = joints.chain_value(j.axis)
            if not j.limits[0] <= value <= j.limits[1]:
                raise ValueError(f"{j.axis} = {value:g} {AXIS_UNITS[j.axis]} is outside the C-arm's "
                                 f"range [{j.limits[0]:g}, {j.limits[1]:g}]")
        sid = self.sid(joints)
        if not self.sid_limits_mm[0] <= sid <= self.sid_limits_mm[1]:
            raise ValueError(f"SID {sid:g} mm is outside {self.sid_limits_mm}")

    def sid(self, joints: JointReading) -> float:
        return self.sid_nominal_mm if joints.sid_mm is None else joints.sid_mm

    def sd(self) -> np.ndarray:
        """1-sigma uncertainty of each chain joint, in chain order (deg or mm)."""
        return np.array([j.sd for j in self.chain])

    def vector(self, joints: JointReading) -> np.ndarray:
        """The chain joints' values in chain order."""
        return np.array([joints.chain_value(j.axis) for j in self.chain])

    def with_vector(self, joints: JointReading, values: np.ndarray) -> JointReading:
        return replace(joints, **{JOINT_FIELD[j.axis]: float(v) for j, v in zip(self.chain, values)})

    # -- poses ------------------------------------------------------------------------------
    def T_carm_C(self, joints: JointReading) -> Pose:
        """Pose of the C (the frame that carries source and detector) in ``carm``."""
        T = Pose.identity()
        for j in self.chain:
            T = T @ j.transform(joints.chain_value(j.axis))
        return T

    def T_carm_cam(self, joints: JointReading) -> Pose:
        """Pose of the X-ray source (camera frame of README.md, Conventions) in ``carm``."""
        self.check(joints)
        return self.source_pose(joints)

    def source_pose(self, joints: JointReading) -> Pose:
        """:meth:`T_carm_cam` without the range check (for derivatives at the limits)."""
        mount = Pose(rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(self.detector_roll_deg)),
                     np.array([0.0, 0.0, -self.source_to_isocentre_mm]))
        return self.T_carm_C(joints) @ mount

    def isocentre(self, joints: JointReading) -> np.ndarray:
        """The isocentre in ``carm``: on the beam, ``source_to_isocentre_mm`` from the source."""
        return self.T_carm_cam(joints).apply(np.array([0.0, 0.0, self.source_to_isocentre_mm]))

    # -- configuration ----------------------------------------------------------------------
    def to_config(self) -> dict:
        return {"name": self.name, "source_to_isocentre_mm": self.source_to_isocentre_mm,
                "sid_nominal_mm": self.sid_nominal_mm, "sid_limits_mm": list(self.sid_limits_mm),
                "sid_sd_mm": self.sid_sd_mm, "detector_roll_deg": self.detector_roll_deg,
                "chain": [j.to_config() for j in self.chain]}

    @staticmethod
    def from_config(d: Mapping) -> CArmKinematics:
        """A model from a configuration table; absent keys take the mobile C-arm defaults."""
        check_keys(d, {"name", "source_to_isocentre_mm", "sid_nominal_mm", "sid_limits_mm",
                        "sid_sd_mm", "detector_roll_deg", "chain"}, "C-arm kinematics")
        kwargs = {k: v for k, v in d.items() if k != "chain"}
        if not isinstance(kwargs.get("name", ""), str):
            raise ValueError(f"C-arm kinematics: name must be a string, got {kwargs['name']!r}")
        for key in kwargs.keys() - {"name", "sid_limits_mm"}:
            kwargs[key] = config_number(kwargs[key], f"C-arm kinematics: {key}")
        if "chain" in d:
            if not isinstance(d["chain"], (list, tuple)):
                raise ValueError(f"C-arm kinematics: chain must be a list of joints, got {d['chain']!r}")
            kwargs["chain"] = tuple(ChainJoint.from_config(j) for j in d["chain"])
        return CArmKinematics(**kwargs)


# -- patient set-up and initial view poses -----------------------------------------------------


@dataclass(frozen=True)
class PatientSetup:
    """Where the tibia lies in ``carm``: supine, the knee at the reference view's isocentre.

    ``superior_carm`` is the direction of the tibia's mechanical axis (ankle to knee, which
    points towards the head) and ``anterior_carm`` the patient's anterior, both in ``carm``;
    ``isocentre_in_anat_mm`` is where the isocentre sits in the anatomical frame (the knee
    centre by default). ``rot_sd_deg``/``trans_sd_mm`` state how well this holds in practice.
    """

    T_tibia_anat: Pose
    superior_carm: tuple[float, float, float] = (0.0, -1.0, 0.0)
    anterior_carm: tuple[float, float, float] = (0.0, 0.0, 1.0)
    isocentre_in_anat_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_view: int = 0
    rot_sd_deg: float = 5.0
    trans_sd_mm: float = 20.0

    def __post_init__(self) -> None:
        s = _vector(self.superior_carm, "superior_carm", True)
        a = _vector(self.anterior_carm, "anterior_carm", True)
        if abs(np.dot(s, a)) > 1e-6:
            raise ValueError("superior_carm and anterior_carm must be perpendicular")
        object.__setattr__(self, "superior_carm", tuple(s))
        object.__setattr__(self, "anterior_carm", tuple(a))
        object.__setattr__(self, "isocentre_in_anat_mm",
                           tuple(_vector(self.isocentre_in_anat_mm, "isocentre_in_anat_mm")))
        for name in ("rot_sd_deg", "trans_sd_mm"):
            if config_number(getattr(self, name), name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        reference = config_number(self.reference_view, "reference_view", integer=True)
        if reference < 0:
            raise ValueError(f"reference_view must be a view index (0, 1, ...), got {reference}")
        object.__setattr__(self, "reference_view", reference)

    @staticmethod
    def from_config(landmarks: Landmarks, d: Mapping) -> PatientSetup:
        check_keys(d, {"superior_carm", "anterior_carm", "isocentre_in_anat_mm", "reference_view",
                        "rot_sd_deg", "trans_sd_mm"}, "patient set-up")
        return PatientSetup(landmarks.T_tibia_anat(), **d)

    def R_carm_anat(self) -> np.ndarray:
        z, y = np.asarray(self.superior_carm), np.asarray(self.anterior_carm)
        return np.column_stack([np.cross(y, z), y, z])

    def T_carm_anat(self, kinematics: CArmKinematics, reference: JointReading) -> Pose:
        R = self.R_carm_anat()
        return Pose(R, kinematics.isocentre(reference) - R @ np.asarray(self.isocentre_in_anat_mm))


@dataclass(frozen=True)
class RelativePose:
    """The uncertainty of the encoders' motion between two views.

    The motion itself, ``T_camB_camA`` (view A's camera frame into view B's), is that of the
    poses :func:`initial_view_poses` returns: ``T_cam_tibia[b] @ T_cam_tibia[a].inverse()``.
    ``covariance`` (6x6, order translation mm then rotation vector rad) is that of the error
    this motion implies for the tibia, expressed in the anatomical frame at the knee — the
    residual of the solver's relative-pose term — propagated from the joint uncertainties of
    both views.
    """

    view_a: int
    view_b: int
    covariance: np.ndarray

    @property
    def sigma_mm(self) -> float:
        """Largest 1-sigma translation error at the knee (mm)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.covariance[:3, :3])[-1]))

    @property
    def sigma_rad(self) -> float:
        """Largest 1-sigma rotation error (rad)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.covariance[3:, 3:])[-1]))


def _relative_covariance(kinematics: CArmKinematics, ja: JointReading, jb: JointReading,
                         T_camA_anat: Pose) -> np.ndarray:
    """Covariance of the knee-frame error of ``T_camB_camA`` by central differences.

    With ``M`` the nominal and ``M~`` a measured motion, the tibia seen from view B and
    carried back to view A is displaced by ``D = T_camA_anat^-1 M~^-1 M T_camA_anat``.
    """
    def motion(qa: np.ndarray, qb: np.ndarray) -> Pose:
        return (kinematics.source_pose(kinematics.with_vector(jb, qb)).inverse()
                @ kinematics.source_pose(kinematics.with_vector(ja, qa)))

    q = np.concatenate([kinematics.vector(ja), kinematics.vector(jb)])
    n = len(kinematics.chain)
    M = motion(q[:n], q[n:])

    def error(qq: np.ndarray) -> np.ndarray:
        D = T_camA_anat.inverse() @ motion(qq[:n], qq[n:]).inverse() @ M @ T_camA_anat
        return np.concatenate([D.t, so3_log(D.R)])

    step = 1e-3  # deg or mm: far below any joint uncertainty, far above rounding
    steps = np.eye(2 * n) * step
    J = np.column_stack([error(q + e) - error(q - e) for e in steps]) / (2 * step)
    sd = np.tile(kinematics.sd(), 2)
    cov = (J * sd**2) @ J.T
    return 0.5 * (cov + cov.T)


def initial_view_poses(kinematics: CArmKinematics, joints_per_view: Sequence[JointReading],
                       setup: PatientSetup) -> tuple[list[Pose], list[RelativePose]]:
    """Each view's ``T_cam_tibia`` from the encoders and the nominal set-up, and the
    uncertainty of the motion between every pair of views (i < j).

    The absolute poses carry the set-up's uncertainty (degrees, centimetres); the relative
    motion does not depend on the set-up at all, which is why it is known much better.
    """
    if len(joints_per_view) < 1:
        raise ValueError("initial_view_poses needs the joints of at least one view")
    if not 0 <= setup.reference_view < len(joints_per_view):
        raise ValueError(f"reference view {setup.reference_view} is not one of the "
                         f"{len(joints_per_view)} views")
    T_carm_anat = setup.T_carm_anat(kinematics, joints_per_view[setup.reference_view])
    T_anat_tibia = setup.T_tibia_anat.inverse()
    T_carm_cam = [kinematics.T_carm_cam(j) for j in joints_per_view]
    poses = [T.inverse() @ T_carm_anat @ T_anat_tibia for T in T_carm_cam]
    relatives = []
    for a in range(len(joints_per_view)):
        for b in range(a + 1, len(joints_per_view)):
            T_camA_anat = T_carm_cam[a].inverse() @ T_carm_anat
            cov = _relative_covariance(kinematics, joints_per_view[a], joints_per_view[b], T_camA_anat)
            relatives.append(RelativePose(a, b, cov))
    return poses, relatives


# -- DICOM positioner angles -------------------------------------------------------------------


def dicom_angles(kinematics: CArmKinematics, joints: JointReading,
                 setup: PatientSetup) -> tuple[float, float]:
    """(PositionerPrimaryAngle, PositionerSecondaryAngle) in degrees implied by the joints.

    DICOM PS3.3 C.8.7.5.1.2 places the image intensifier (detector) about the patient like
    longitude and latitude: primary 0 = anterior, +90 = the patient's left (LAO); secondary
    +90 = cranial. With ``d`` the unit direction from the isocentre to the detector:
    ``primary = atan2(d.left, d.anterior)``, ``secondary = asin(d.superior)``.
    """
    d = kinematics.T_carm_cam(joints).rotate(np.array([0.0, 0.0, 1.0]))
    superior, anterior = np.asarray(setup.superior_carm), np.asarray(setup.anterior_carm)
    left = np.cross(superior, anterior)
    primary = np.degrees(np.arctan2(d @ left, d @ anterior))
    secondary = np.degrees(np.arcsin(np.clip(d @ superior, -1.0, 1.0)))
    return float(primary), float(secondary)


def _beam(primary_deg: float, secondary_deg: float) -> np.ndarray:
    """Detector direction in (left, anterior, superior) components from DICOM angles."""
    p, s = np.radians(primary_deg), np.radians(secondary_deg)
    return np.array([np.sin(p) * np.cos(s), np.cos(p) * np.cos(s), np.sin(s)])


@dataclass(frozen=True)
class AngleCheck:
    """Encoder angles against a frame's DICOM positioner angles."""

    status: str  # "agrees", "disagrees" or "not_available"
    encoder_deg: tuple[float, float]
    dicom_deg: tuple[float | None, float | None]
    beam_difference_deg: float | None  # angle between the two beam directions
    threshold_deg: float
    message: str

    @property
    def agrees(self) -> bool:
        return self.status == "agrees"

    def to_json(self) -> dict:
        return {"status": self.status, "encoder_primary_deg": self.encoder_deg[0],
                "encoder_secondary_deg": self.encoder_deg[1], "dicom_primary_deg": self.dicom_deg[0],
                "dicom_secondary_deg": self.dicom_deg[1],
                "beam_difference_deg": self.beam_difference_deg, "threshold_deg": self.threshold_deg,
                "message": self.message}


def check_dicom_angles(kinematics: CArmKinematics, joints: JointReading, setup: PatientSetup,
                       primary_deg: float | None, secondary_deg: float | None,
                       threshold_deg: float = 2.0) -> AngleCheck:
    """Compare the beam direction of the encoders with the one a DICOM header states.

    The comparison is on the beam direction (not angle by angle), so it is well defined near
    the poles where the primary angle is not. Absent header angles give "not_available".
    """
    if not threshold_deg > 0:
        raise ValueError(f"the angle threshold must be positive, got {threshold_deg}")
    enc = dicom_angles(kinematics, joints, setup)
    if primary_deg is None or secondary_deg is None:
        return AngleCheck("not_available", enc, (primary_deg, secondary_deg), None, threshold_deg,
                          "the frame carries no PositionerPrimaryAngle/PositionerSecondaryAngle")
    for name, value in (("primary", primary_deg), ("secondary", secondary_deg)):
        if not np.isfinite(value):
            raise ValueError(f"DICOM positioner {name} angle {value!r} is not a number")
    cos = float(np.clip(_beam(*enc) @ _beam(primary_deg, secondary_deg), -1.0, 1.0))
    diff = float(np.degrees(np.arccos(cos)))
    status = "agrees" if diff <= threshold_deg else "disagrees"
    message = (f"encoders give primary {enc[0]:+.1f}, secondary {enc[1]:+.1f} deg; the DICOM header "
               f"says {primary_deg:+.1f}, {secondary_deg:+.1f} deg: beams {diff:.1f} deg apart "
               f"({'within' if status == 'agrees' else 'beyond'} the {threshold_deg:g} deg threshold)")
    return AngleCheck(status, enc, (float(primary_deg), float(secondary_deg)), diff, threshold_deg,
                      message)
