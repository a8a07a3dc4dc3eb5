"""The joint solver: both C-arm views, both pins and every edge point at once.

Problem layout (docs/solver.md): poses ``[T_cam0_tibia, ..., T_camV-1_tibia,
T_tibia_pin1, T_tibia_pin2]`` and one 3D point per kept contour pixel (bone points in the
tibia frame, pin points in their pin's frame). The schedule:

1. each view's bone found in its image by an exhaustive shift/rotation search;
2. silhouettes alone (E_mp, poses only): the views on the bone (annealed robust scale,
   tied together by the encoders' relative motion E_odo) — a bone still off its contours
   here means the start was too far, and the solve stops; the pins triangulated from the
   ends of their contours and refined; then every silhouette at once;
3. edge points seated on their observed rays where each ray grazes its model;
4. joint Levenberg-Marquardt on ``w_rp E_rp + w_bp E_bp + w_mp E_mp (+ E_odo)``, with the
   silhouettes traced once at its start (the problem is then smooth), the points seated
   again after a few iterations at the poses reached and the stage run again from there,
   and again while a stage still turns the poses (its held depths are then stale);
5. quality gates (:mod:`.gates`), the resection plane, and its covariance-based uncertainty.

A solve that went astray (stopped at step 2, did not converge, or whose outlines do not
fit) is run again from a global search of the patient set-up (:mod:`.setup_search`).

A pin's roll about its own axis is unobservable (a cylinder), so that direction is fixed.

``SolverConfig.method`` selects the proposed method or one of the paper's baselines
(``METHODS``); all share the global alignment, the pin triangulation, the optimiser, the
quality gates and the uncertainty.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from slamtka.solver import gates
from slamtka.solver.alignment import align_view_in_image
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.measurement import ResectionPlane, angle_covariance, fit_resection_plane
from slamtka.solver.observations import LABELS, PIN_LABELS, ViewObservation
from slamtka.solver.optimizer import (
    IterationInfo,
    LMOptions,
    RobustLoss,
    SharedError,
    SolveReport,
    State,
    Term,
    levenberg_marquardt,
    pose_covariance,
)
from slamtka.solver.pin_naming import naming_clear, naming_score, settle_naming, swap_pays, swap_pins
from slamtka.solver.plan import Plan, RigidModel
from slamtka.solver.setup_search import SetupSearch, search_setup
from slamtka.solver.terms import BackProjectionTerm, ModelProjectionTerm, RelativePoseTerm, ReprojectionTerm
from slamtka.solver.triangulation import PinSighting, triangulate_pin

__all__ = ["METHODS", "InitialGuess", "SolverConfig", "SolveOutcome", "solve_joint", "thin_contour"]

# Coarse ray search in seat_on_rays: steps this many times the fine step.
_SEAT_COARSE = 4

log = logging.getLogger("slamtka.solver")

# The proposed method, the same without the encoder odometry factor, and the paper's four
# baselines: model projection only (E_mp) or contour back-projection only (E_rp + E_bp), each
# "split" (views from the bone first, then the pins with the views held) or "joint".
METHODS = ("slam", "slam-noenc", "projection-split", "projection-joint",
           "backprojection-split", "backprojection-joint")


@dataclass(frozen=True)
class InitialGuess:
    """Starting poses: each view from the encoders, each pin from the planned resection.

    ``odometry_sigma`` (rad, mm), when given, says that the motion between the views'
    poses was measured by the C-arm's encoders with that uncertainty (about the knee); the
    solver then keeps it as a relative-pose factor (E_odo), not only as a starting point.
    """

    T_cam_tibia: tuple[Pose, ...]
    T_tibia_pin: tuple[Pose, Pose]
    odometry_sigma: tuple[float, float] | None = None


@dataclass(frozen=True)
class SolverConfig:
    sigma_px: float = 2.0  # expected contour noise, pixels
    # Expected distance of a true edge point to the bone's surface (the bone's own mesh and
    # its decimated copy). Converged solves leave 0.27 mm RMS, but 0.3 mm made the reported
    # sigma too small for the phantom (58-66% of its errors within 1 sigma, 90-95% within 2,
    # over 1,000 study runs), whose contour noise also biases STR by 0.1-0.2 deg in some
    # cases (the silhouette's distance to a noisy contour), while the real tibia stayed
    # over-covered (75-84%). 0.5 mm errs on the side of a wider sigma. Smooth segmentation
    # error is a separate, shared error (``Plan.segmentation_sd_mm``).
    sigma_mm: float = 0.5
    # ... and to a pin's: a machined part, its mesh and distance field true to ~0.05 mm.
    pin_sigma_mm: float = 0.1
    # Distance over which the plan's bone segmentation error (``Plan.segmentation_sd_mm``)
    # stays alike: CT segmentation errors follow partial-volume blur, thresholds and
    # smoothing over a few voxels to centimetres.
    segmentation_correlation_mm: float = 10.0
    sigma_depth_mm: float = 0.5  # ... and of its depth along the ray from where it grazes
    # A bone contour pixel whose ray passes further than this from the bone at the poses
    # where the edge points are seated is not the bone's edge (a soft-tissue border, the gap
    # between tibia and fibula, a speck): it gets no edge point. Simulated contours with
    # 2 px of noise seat within 1.4 mm at the coarse poses; the stray points of bone
    # contours extracted from radiographs (1-7% of them) lie up to tens of millimetres off,
    # and under E_bp's Huber loss their constant pull tilted the views (service path: STR
    # +0.34 deg, +0.22 deg without them). Pin contours are fitted bars, without strays: a
    # pin point off its pin is a wrong pose, and stays for the gates to see.
    max_ray_miss_mm: float = 3.0
    # ... but a bone contour with more than this share of such pixels at the final poses is
    # not the bone's outline (or the poses are wrong): the solve is refused.
    max_stray_fraction: float = 0.2
    w_rp: float = 1.0
    w_bp: float = 1.0
    w_mp: float = 0.1
    edge_spacing_px: float = 6.0  # observed contours are thinned to this spacing
    silhouette_spacing_px: float = 5.0
    # The silhouette stages before the joint one only bring the models into its basin: they
    # sample the observed contours and the traced outlines this many times more sparsely
    # (the per-point work of an iteration halves; over 150 paired phantom solves at levels
    # 1-5 the final errors did not change).
    coarse_thinning: float = 2.0
    # The bone's stages: each robust scale is a step of an annealing, not a solve to its end
    # (10 iterations per scale, as before, cost 11 more iterations per solve at the median
    # of 150 phantom solves at levels 1-5, for the same final errors).
    coarse: LMOptions = LMOptions(max_iterations=5, relative_tolerance=1e-3)
    # The pins start triangulated from their contours: their own stage is a short polish
    # (longer only crawls; every silhouette is refined together next).
    coarse_pins: LMOptions = LMOptions(max_iterations=4, relative_tolerance=1e-3)
    coarse_loss_scales: tuple[float, ...] = (20.0, 6.0, 2.0)  # Cauchy scales, in sigmas
    light_mesh_min_scale: float = 10.0  # bone stages at this scale or wider trace the light mesh
    # Every silhouette at once, the start of the joint stage (which settles the plane).
    coarse_all: LMOptions = LMOptions(max_iterations=10, relative_tolerance=1e-3)
    # The joint stages' damping never falls below 1e-3 of the diagonal: near their end the
    # Gauss-Newton model of the edge points on the pins' curved surfaces promises several
    # per cent and delivers nothing, and each refused step from a smaller damping is a wasted
    # evaluation (11.7 trial steps per solve fell to 7.9; final errors unchanged over 150
    # paired phantom solves).
    fine: LMOptions = LMOptions(max_iterations=60, relative_tolerance=5e-3, step_tolerance=1e-3,
                                min_lambda=1e-3)
    # The joint stage's edge points are held at the depth where their rays grazed the model
    # at the coarse poses; after this many iterations they are seated again at the poses
    # reached, and the stage run again from there (held at stale depths, they pull the poses
    # back towards those they were seated at)...
    joint_seated_iterations: int = 3
    # ... and seated again, each time the stage has converged, while it turned a view or a
    # pin by more than this since the points were seated, up to ``max_seatings`` in all.
    # Each seating closes about half of the remaining gap: stopping after the second left
    # the views 0.1-0.3 deg (a slightly-off start, up to 0.9 deg) short of where the
    # contours put them; seating until the stage turns nothing by more than 0.1 deg cut the
    # phantom's STR spread from 0.13 to 0.09 deg (150 paired solves at levels 1-5) and
    # brought a case refused for its pins' disagreeing views back to a measurement.
    reseat_turn_deg: float = 0.1
    max_seatings: int = 5
    # The joint stages end once an iteration moves neither angle by more than this: the edge
    # points go on creeping along the curved pin surfaces (small cost decreases, rejected
    # Gauss-Newton steps) long after the resection plane stopped moving.
    settled_angle_deg: float = 0.005
    min_view_separation_deg: float = 15.0
    min_bone_points: int = 50
    min_pin_points: int = 20
    max_residual_rms_px: float = 4.0  # re-projection RMS above this: contours do not fit
    max_silhouette_median_px: float = 2.5  # a model's outline this far off its contour: no fit
    # ... and a tenth of a pin's outline this far off (~13 mm at the detector): a pin is seen
    # whole, so much of its outline far from any contour is a wrong pose, however well the
    # rest lies (a pin turned about the end it shares with its contour keeps the median
    # small). Pin contours extracted from radiographs miss up to ~42 px of a pin's end (40 px
    # refused 2 of 20 correct imaging-chain solves), and wrong poses seen in the studies left
    # 130-250 px; 6 px also refused slightly-off fits.
    max_pin_outline_p90_px: float = 60.0
    # A pin's edge points this far (RMS) from where their rays graze it (off its surface, or
    # slid along their rays from the grazing depth): a machined part, seen consistently in
    # every view, lies within ~0.1 mm of its points; its contours disagreeing about where it
    # is by more means a view's pose is wrong. Over 200 study solves correct ones left at
    # most 0.3 mm; those caught with a view 1 deg off left 4-6 mm (points slid along their
    # rays, within 0.6 mm of the surface) and STR 0.3-0.6 deg off, 3-5 sigma; a wrong basin
    # of the real tibia left 1.2 mm off the surface.
    max_pin_graze_offset_mm: float = 0.8
    # The cutting block's guide holes hold its two pins parallel, and the cut is measured as
    # parallel to their plane: pins found further from parallel than this mean a pin pose is
    # wrong (or the premise of the measurement does not hold). Correct solves left them at
    # most 0.45 deg apart on simulated contours (150 real-tibia study solves); a wrong basin
    # seen without the encoder factor (one pin 31 deg off, its outline a tenth off by 40 px,
    # under the pin gate) 28 deg. On contours extracted from rendered radiographs (60 solves
    # of `bench imaging`) all but one stayed within 2.1 deg; that one, 3.3 deg, is sent to the
    # global search, which measures it better (with an 8 deg limit instead, its level's p95
    # rose from 0.25 to 0.38 deg STR and from 0.13 to 0.17 deg CTR).
    max_pin_divergence_deg: float = 3.0
    # The encoders' motion between the views (E_odo) left further off than this (whitened
    # RMS over the views' relative poses, in sigmas: 6 components each): the contours were
    # fitted by poses the C-arm did not move through, a local minimum. Refused as astray, so
    # the global search restarts it. Correct solves of simulated contours left at most 5.2
    # (190 study solves, phantom and real tibia, levels 1-5, median 2.5); a held-out solve
    # 0.8 deg off (8 sigma) left 8.9. Extracted contours carry a bias the model does not
    # know: one `bench imaging` case left 6.9-7.0, measured 0.41 deg off (4.7 sigma), which
    # a limit of 6 refused; 7.5 keeps it and still refuses the held-out one.
    max_odometry_rms_sigma: float = 7.5
    max_coarse_bone_median_px: float = 4.0  # ... the bone's, after its own stage: gone astray
    # Bone contour pixels this far from the tibia's outline after the bone's own stage are
    # another body's edges (femur, patella, metal, collimator) and are dropped before the
    # pins and the joint stages (None: keep every pixel). Simulated 2 px contour noise
    # leaves the tibia's own pixels within ~8 px there.
    foreign_edge_px: float | None = 15.0
    max_angle_sigma_deg: float = 2.0
    # Restarts from a global set-up search when the solve goes astray (none: no restart):
    # first within +-30 deg of the encoders' guess, then, each if the last fails too, +-60
    # and +-90 deg (0.5 rad of set-up error per axis reaches 80 deg in one case in 100).
    global_searches: tuple[SetupSearch, ...] = (
        SetupSearch(), SetupSearch(coarse_half_range_deg=60.0, coarse_step_deg=20.0, refinements=3),
        SetupSearch(coarse_half_range_deg=90.0, coarse_step_deg=30.0, refinements=4, rescored=16))
    method: str = "slam"  # one of METHODS

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")


@dataclass
class SolveOutcome:
    """Everything the solve produced; ``status`` is ``measured`` or ``not_measured``."""

    status: str
    reason: str
    state: State | None
    T_cam_tibia: list[Pose]
    T_tibia_pin: list[Pose]
    plane: ResectionPlane | None
    angle_cov: np.ndarray | None  # (2, 2) rad^2 of (CTR, STR)
    residual_rms: dict[str, float]
    term_costs: dict[str, float]
    iterations: int
    seconds: float
    converged: bool
    convergence_reason: str
    point_counts: dict[str, int] = field(default_factory=dict)
    # Of those, the ones that kept an edge point in the final energy (the rest strayed off
    # the bone); empty for methods without edge points and for solves never run.
    edge_point_counts: dict[str, int] = field(default_factory=dict)
    initialisation: str = "encoders"  # or "global set-up search" when the first solve went astray
    went_astray: bool = False  # refused because the solve lost its way, not for the geometry
    renamed: list[str] = field(default_factory=list)  # views whose pin names were swapped
    unclear_naming: list[str] = field(default_factory=list)  # views whose pin names were open

    @property
    def angles_deg(self) -> tuple[float, float] | None:
        """(CTR, STR) in degrees, when a plane was fitted."""
        if self.plane is None:
            return None
        return float(np.degrees(self.plane.ctr)), float(np.degrees(self.plane.str_))


def thin_contour(pixels: np.ndarray, spacing_px: float) -> np.ndarray:
    """Keep one observed edge pixel per ``spacing_px`` grid cell (order preserved)."""
    if len(pixels) == 0:
        return pixels
    cells = np.floor(pixels / spacing_px).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return pixels[np.sort(first)]


def _ray_depths_in_box(rays: np.ndarray, T_body_cam: Pose, box: np.ndarray) -> np.ndarray:
    """Depth interval (N, 2) in which each camera ray ``z * ray`` (unit-depth rays) crosses the
    body-frame box ``box`` (2, 3) (slab test). A ray that misses the box gets the empty
    interval at its closest approach to the box's centre."""
    origin = T_body_cam.t
    direction = rays @ T_body_cam.R.T  # body-frame direction per unit depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - origin) / direction
        t1 = (box[1] - origin) / direction
    # An axis the ray runs parallel to constrains nothing if the source lies within its slab.
    parallel = direction == 0
    inside = (origin >= box[0]) & (origin <= box[1])
    t0 = np.where(parallel, np.where(inside, -np.inf, np.inf), t0)
    t1 = np.where(parallel, np.where(inside, np.inf, -np.inf), t1)
    near = np.max(np.minimum(t0, t1), axis=1)
    far = np.min(np.maximum(t0, t1), axis=1)
    missed = ~(far >= near)
    if np.any(missed):
        centre = box.mean(axis=0) - origin
        closest = direction[missed] @ centre / np.sum(direction[missed] ** 2, axis=1)
        near[missed] = far[missed] = closest
    return np.column_stack([near, far])


def seat_on_rays(
    model: RigidModel, T_cam_body: Pose, camera: Camera, pixels: np.ndarray, step_mm: float
) -> np.ndarray:
    """Body-frame 3D points on the rays of ``pixels`` where each ray grazes the model.

    Each ray's point is where the model's signed distance along it is least: the tangent
    point of a ray that grazes, the deepest point of one that just cuts in (so noise on
    either side of the outline is charged alike), the closest approach of one that misses.
    Each ray is searched where it crosses the distance field's box, at ``_SEAT_COARSE``
    steps, then at ``step_mm`` around the best, then refined to the vertex of a parabola.
    """
    rays = camera.rays(pixels)
    rays = rays / rays[:, 2:3]  # unit depth
    T_body_cam = T_cam_body.inverse()
    # A model that went behind the source (a solve gone astray) still gets points, at the
    # nearest depth searched; the gates then refuse the solve.
    depths = np.maximum(_ray_depths_in_box(rays, T_body_cam, model.sdf.bounds()), 10.0)

    def distances(z: np.ndarray) -> np.ndarray:
        """Signed distances (rays, samples) at depths ``z`` (rays, samples)."""
        samples = (rays[:, None, :] * z[:, :, None]).reshape(-1, 3)
        return model.sdf.query(T_body_cam.apply(samples), gradient=False)[0].reshape(z.shape)

    coarse_step = _SEAT_COARSE * step_mm
    samples = int(np.ceil(np.max(depths[:, 1] - depths[:, 0]) / coarse_step)) + 1
    z = np.minimum(depths[:, :1] + coarse_step * np.arange(samples), depths[:, 1:])
    rows = np.arange(len(pixels))
    around = z[rows, np.argmin(distances(z), axis=1)]
    offsets = np.arange(-_SEAT_COARSE, _SEAT_COARSE + 1) * step_mm
    z_fine = around[:, None] + offsets[None, :]
    d = distances(z_fine)
    best = np.clip(np.argmin(d, axis=1), 1, len(offsets) - 2)
    # Near a grazing point the distance along the ray is a parabola: refine to its vertex.
    d_minus, d_0, d_plus = d[rows, best - 1], d[rows, best], d[rows, best + 1]
    curvature = d_plus - 2.0 * d_0 + d_minus
    shift = np.where(curvature > 1e-9, 0.5 * (d_minus - d_plus) / np.maximum(curvature, 1e-9), 0.0)
    depth = z_fine[rows, best] + np.clip(shift, -1.0, 1.0) * step_mm
    return T_body_cam.apply(rays * depth[:, None])


class EdgeGroup(NamedTuple):
    """The edge points of one model in one view: their ids among the state's points, the
    contour pixels they were seated from and their rays' directions (model frame)."""

    ids: np.ndarray
    pixels: np.ndarray
    directions: np.ndarray


class JointProblem:
    """Variables, terms and gauge of one solve, built from a plan and the views."""

    def __init__(self, plan: Plan, views: list[ViewObservation], config: SolverConfig,
                 naming_fixed: bool = False):
        """``naming_fixed``: take the views' pin names as given (no :meth:`relabelled`)."""
        self.plan, self.views, self.config = plan, list(views), config
        self.naming_fixed = naming_fixed
        self.bone = plan.bone_model()
        self.pin = plan.pin_model()
        self.n_views = len(views)
        self.pixels = {(k, label): thin_contour(v.contours[label], config.edge_spacing_px)
                       for k, v in enumerate(views) for label in LABELS}
        # ... and more sparsely for the coarse silhouette stages (SolverConfig.coarse_thinning).
        self.coarse_pixels = {key: thin_contour(px, config.edge_spacing_px * config.coarse_thinning)
                              for key, px in self.pixels.items()}

    def attributed(self, poses: tuple[Pose, ...]) -> JointProblem:
        """The problem without the bone contour pixels that no part of the tibia's outline,
        traced at ``poses``, comes near (``SolverConfig.foreign_edge_px``): the edges of a
        femur, a patella, a retractor or a collimator blade that extraction could not tell
        from the tibia's. Only views whose traced outline lies on their contour (median
        ``max_coarse_bone_median_px``) are pruned: a model off its contour says nothing
        about which edges are its own. ``self`` when nothing is dropped."""
        c = self.config
        views = list(self.views)
        for k, view in enumerate(self.views):
            pixels = view.contours["bone"]
            if len(pixels) == 0:
                continue
            T = poses[k]
            outline = self.bone.contour.outline_points(T, view.camera, c.silhouette_spacing_px,
                                                       outer_only=True)
            if len(outline) == 0:
                continue
            uv = view.camera.project(T.apply(outline))
            if float(np.median(view.distance_map("bone").query(uv)[0])) > c.max_coarse_bone_median_px:
                continue
            near = cKDTree(uv).query(pixels)[0] <= c.foreign_edge_px
            if near.all():
                continue
            views[k] = ViewObservation(view.view_id, view.camera, {**view.contours, "bone": pixels[near]},
                                       view.notes)
        if all(a is b for a, b in zip(views, self.views)):
            return self
        return JointProblem(self.plan, views, c, self.naming_fixed)

    def point_counts(self) -> dict[str, int]:
        """Kept contour points per view and label, for the result document."""
        return self.named({key: len(px) for key, px in self.pixels.items()})

    def named(self, counts: dict[tuple[int, str], int]) -> dict[str, int]:
        """Counts per (view index, label) keyed as the result document names them."""
        return {f"{self.views[k].view_id}/{label}": n for (k, label), n in counts.items()}

    def edge_point_counts(self, terms: list[Term]) -> dict[tuple[int, str], int]:
        """Contour points per view and label that kept an edge point in ``terms`` (those of
        the re-projection terms; empty for methods without edge points)."""
        return {(t.view, self.label(t.body)): len(t.pixels)
                for t in terms if isinstance(t, ReprojectionTerm)}

    def body_index(self, label: str) -> int | None:
        return None if label == "bone" else self.n_views + PIN_LABELS.index(label)

    def label(self, body: int | None) -> str:
        """The label of the body at pose index ``body`` (the inverse of :meth:`body_index`)."""
        return "bone" if body is None else PIN_LABELS[body - self.n_views]

    def model(self, label: str) -> RigidModel:
        return self.bone if label == "bone" else self.pin

    def fixed_dofs(self, views: bool = False, pins: bool = False) -> np.ndarray:
        """Mask of parameters held fixed: always each pin's roll about its own axis (a gauge
        direction), and optionally all view or all pin parameters (staged solves)."""
        fixed = np.zeros((self.n_views + 2, 6), bool)
        fixed[: self.n_views] = views
        fixed[self.n_views:] = pins
        fixed[self.n_views:, 5] = True
        return fixed.reshape(-1)

    def T_cam_body(self, poses: tuple[Pose, ...], k: int, label: str) -> Pose:
        body = self.body_index(label)
        return poses[k] if body is None else poses[k] @ poses[body]

    def relabelled(self, poses: tuple[Pose, ...]) -> tuple[JointProblem, list[str], list[str]]:
        """The problem with the two pins' names swapped in each view where the swap makes
        both pins' sightings meet clearly better (views posed from the bone alone; names
        from extraction's guess; :mod:`solver.pin_naming`). Also the ids of the views
        swapped, and of those whose naming is not clear either way."""
        if self.naming_fixed:
            return self, [], []
        length, view_poses = self.plan.pin_length(), poses[: self.n_views]
        views, swapped, unclear = list(self.views), [], []
        for k in range(1, self.n_views):
            trial = views[:k] + [swap_pins(views[k])] + views[k + 1:]
            kept, changed = naming_score(views, view_poses, length), naming_score(trial, view_poses, length)
            if swap_pays(kept, changed):
                views, swapped, kept, changed = trial, swapped + [views[k].view_id], changed, kept
            if not naming_clear(kept, changed):
                unclear.append(views[k].view_id)
        problem = JointProblem(self.plan, views, self.config) if swapped else self
        return problem, swapped, unclear

    def triangulated_pins(self, poses: tuple[Pose, ...]) -> tuple[Pose, ...]:
        """Each pin's pose triangulated from its contours in the views at ``poses`` (the
        current pin pose where it cannot be)."""
        pins = []
        for label in PIN_LABELS:
            current = poses[self.body_index(label)]
            sightings = [PinSighting(view.camera, poses[k], self.pixels[k, label])
                         for k, view in enumerate(self.views)]
            pins.append(triangulate_pin(sightings, current, self.plan.pin_length()) or current)
        return tuple(pins)

    def seated_points(self, poses: tuple[Pose, ...], labels: tuple[str, ...] = LABELS
                      ) -> tuple[np.ndarray, dict[tuple[int, str], EdgeGroup]]:
        """Edge points of ``labels`` seated on their rays for ``poses``, and per view and
        label the group of points kept: for the bone, those whose rays pass within
        ``SolverConfig.max_ray_miss_mm`` of it."""
        chunks, groups, start = [], {}, 0
        for (k, label), px in self.pixels.items():
            if len(px) == 0 or label not in labels:
                continue
            step = 1.0 if label == "bone" else 0.25
            model = self.model(label)
            T_cam_body, camera = self.T_cam_body(poses, k, label), self.views[k].camera
            seated = seat_on_rays(model, T_cam_body, camera, px, step)
            kept = np.ones(len(px), bool)
            if label == "bone":
                kept = np.abs(model.sdf.query(seated, gradient=False)[0]) <= self.config.max_ray_miss_mm
            if not kept.any():
                continue
            chunks.append(seated[kept])
            groups[k, label] = EdgeGroup(np.arange(start, start + kept.sum()), px[kept],
                                         T_cam_body.inverse().rotate(camera.rays(px[kept])))
            start += int(kept.sum())
        points = np.vstack(chunks) if chunks else np.zeros((0, 3))
        return points, groups

    def silhouette_terms(self, labels: tuple[str, ...], weight: float, loss: RobustLoss,
                         freeze_outline: bool = False, light: bool = False,
                         thinned: bool = False) -> list[Term]:
        """E_mp of ``labels`` in every view; ``light`` traces the bone's lighter mesh (the
        set-up search's), enough under a wide robust scale (a pin's mesh is light already);
        ``thinned`` samples contours and outlines ``SolverConfig.coarse_thinning`` times
        more sparsely."""
        c = self.config
        thinning = c.coarse_thinning if thinned else 1.0
        terms: list[Term] = []
        for k, view in enumerate(self.views):
            for label in labels:
                if len(view.contours[label]) == 0:
                    continue
                terms.append(ModelProjectionTerm(
                    "E_mp", k, self.body_index(label), view.camera,
                    (self.bone.coarse_contour if light and label == "bone"
                     else self.model(label).contour),
                    view.distance_map(label),
                    (self.coarse_pixels if thinned else self.pixels)[k, label],
                    c.sigma_px, c.silhouette_spacing_px * thinning,
                    outer_only=(label == "bone"), weight=weight, loss=loss,
                    freeze_outline=freeze_outline))
        return terms

    def odometry_terms(self, initial: InitialGuess) -> list[Term]:
        """E_odo between the first view and each other one, if the encoders measured it
        (the proposed method only: ``slam-noenc`` and the baselines ignore it)."""
        if initial.odometry_sigma is None or self.config.method != "slam":
            return []
        sigma_rad, sigma_mm = initial.odometry_sigma
        anchor = self.plan.landmarks.T_tibia_anat()
        first = initial.T_cam_tibia[0]
        return [RelativePoseTerm("E_odo", 0, k, T @ first.inverse(), anchor, sigma_rad, sigma_mm)
                for k, T in enumerate(initial.T_cam_tibia) if k > 0]

    def edge_terms(self, points: np.ndarray, groups: dict[tuple[int, str], EdgeGroup]
                   ) -> list[Term]:
        """E_rp and E_bp of the edge points ``points`` seated by :meth:`seated_points`."""
        c = self.config
        terms: list[Term] = []
        for (k, label), group in groups.items():
            terms.append(ReprojectionTerm("E_rp", k, self.body_index(label), self.views[k].camera,
                                          group.pixels, group.ids, c.sigma_px, c.w_rp))
            sigma_mm = c.sigma_mm if label == "bone" else c.pin_sigma_mm
            terms.append(BackProjectionTerm("E_bp", self.model(label).sdf, group.ids, sigma_mm,
                                            group.directions, points[group.ids],
                                            c.sigma_depth_mm, c.w_bp, view=k,
                                            body=self.body_index(label)))
        return terms


class _SettledAngles:
    """Iteration callback that ends a stage once an accepted step moved neither resection
    angle (CTR, STR) by more than ``SolverConfig.settled_angle_deg``."""

    def __init__(self, problem: JointProblem, state: State):
        self.problem = problem
        self.angles = self._angles(state)

    def _angles(self, state: State) -> np.ndarray:
        plan = self.problem.plan
        plane = fit_resection_plane(list(state.poses[self.problem.n_views:]), plan.pin_length(),
                                    plan.landmarks)
        return np.degrees([plane.ctr, plane.str_])

    def __call__(self, info: IterationInfo) -> str | None:
        angles = self._angles(info.state)
        moved = float(np.max(np.abs(angles - self.angles)))
        self.angles = angles
        limit = self.problem.config.settled_angle_deg
        if moved > limit:
            return None
        return f"resection angles settled (moved {moved:.4f} <= {limit} deg)"


class _Schedule:
    """The stages of each method, run one after another on a shared state.

    Every method starts from the same global image alignment and triangulates the pins
    from their contours once the views are known, so the methods differ only in their
    energy and in what is estimated when. ``run`` returns the final state, the terms of
    the final energy (for the covariance and residuals) and the report of the last stage.
    """

    def __init__(self, problem: JointProblem, initial: InitialGuess,
                 callback: Callable[[str, IterationInfo], None] | None):
        self.problem, self.callback = problem, callback
        self.odometry = problem.odometry_terms(initial)
        self.iterations, self.seconds = 0, 0.0
        self.renamed: list[str] = []  # views whose pin names were swapped
        self.unclear_naming: list[str] = []  # views whose pin names the sightings leave open

    def lm(self, terms: list[Term], state: State, held: np.ndarray, options: LMOptions,
           name: str, until_settled: bool = False) -> tuple[State, SolveReport]:
        """One optimiser stage; with ``until_settled`` it also ends once the resection
        angles stop moving (:class:`_SettledAngles`)."""
        settled = _SettledAngles(self.problem, state) if until_settled else None

        def stage(info: IterationInfo) -> str | None:
            if self.callback is not None:
                self.callback(name, info)
            return None if settled is None else settled(info)

        state, report = levenberg_marquardt(terms, state, held, options, stage)
        self.iterations += report.iterations
        self.seconds += report.seconds
        return state, report

    def with_triangulated_pins(self, state: State) -> State:
        n = self.problem.n_views
        return State(state.poses[:n] + self.problem.triangulated_pins(state.poses), state.points)

    def views_on_bone_silhouette(self, state: State) -> State:
        """Views on the bone's silhouette, with a robust scale shrinking from wide to tight."""
        p = self.problem
        for scale in p.config.coarse_loss_scales:
            terms = p.silhouette_terms(("bone",), 1.0, RobustLoss("cauchy", scale),
                                       light=scale >= p.config.light_mesh_min_scale,
                                       thinned=True)
            state, _ = self.lm(terms + self.odometry, state, p.fixed_dofs(pins=True),
                               p.config.coarse, f"coarse bone x{scale:g}")
        return state

    def run(self, method: str, state: State) -> tuple[State, list[Term], SolveReport]:
        p, c = self.problem, self.problem.config
        tight = RobustLoss("cauchy", c.coarse_loss_scales[-1])
        if method.startswith("backprojection"):
            return self.back_projection(state, split=method.endswith("split"))
        state = self.views_on_bone_silhouette(state)
        if c.foreign_edge_px is not None:
            p = self.problem = p.attributed(state.poses)
        astray = gates.outline_misfit(p, state, ("bone",), c.max_coarse_bone_median_px)
        if astray is not None:
            # Lost already: the caller may restart from a global search at once.
            return state, p.silhouette_terms(("bone",), 1.0, tight), SolveReport(
                False, f"{astray} after the bone stage", self.iterations, 0.0, {}, self.seconds, [])
        p, self.renamed, self.unclear_naming = p.relabelled(state.poses)
        self.problem = p
        for view_id in self.renamed:
            log.info("view %s: the pin labels were swapped to match the other views", view_id)
        state = self.with_triangulated_pins(state)
        pins_options = c.fine if method == "projection-split" else c.coarse_pins
        state, report = self.lm(p.silhouette_terms(PIN_LABELS, 1.0, tight), state,
                                p.fixed_dofs(views=True), pins_options, "coarse pins")
        if method == "projection-split":
            return state, p.silhouette_terms(LABELS, 1.0, tight), report
        if method == "projection-joint":
            terms = p.silhouette_terms(LABELS, 1.0, tight)
            state, report = self.lm(terms, state, p.fixed_dofs(), c.fine, "projection joint")
            return state, terms, report
        # slam: every silhouette at once (the pins tie the views together), then the joint
        # energy with edge points seated where their rays graze the models.
        state, _ = self.lm(p.silhouette_terms(LABELS, 1.0, tight, thinned=True) + self.odometry,
                           state, p.fixed_dofs(), c.coarse_all, "coarse all")
        first = replace(c.fine, max_iterations=c.joint_seated_iterations)
        options, name, seatings = first, "joint", 0
        while True:
            points, groups = p.seated_points(state.poses)
            terms = p.edge_terms(points, groups) + p.silhouette_terms(
                LABELS, c.w_mp, RobustLoss("cauchy", 3.0), freeze_outline=True) + self.odometry
            seated_at = state.poses
            state, report = self.lm(terms, State(state.poses, points), p.fixed_dofs(), options,
                                    name, until_settled=True)
            seatings += 1
            turned_deg = np.degrees(max(T.rotation_angle_to(U)
                                        for T, U in zip(seated_at, state.poses)))
            if seatings >= c.max_seatings or (seatings > 1 and turned_deg <= c.reseat_turn_deg):
                break
            options, name = c.fine, "joint reseated"
        return state, terms, report

    def back_projection(self, state: State, split: bool) -> tuple[State, list[Term], SolveReport]:
        """Edge points seated on their rays, E_rp + E_bp only: split (views from the bone
        points, then the pins' points with the views held) or joint (everything at once)."""
        p, c = self.problem, self.problem.config
        if split:
            points, groups = p.seated_points(state.poses, labels=("bone",))
            state, _ = self.lm(p.edge_terms(points, groups), State(state.poses, points),
                               p.fixed_dofs(pins=True), c.fine, "back-projection views")
        state = self.with_triangulated_pins(state)
        points, groups = p.seated_points(state.poses)
        terms = p.edge_terms(points, groups)
        held = p.fixed_dofs(views=True) if split else p.fixed_dofs()
        name = "back-projection pins" if split else "back-projection joint"
        state, report = self.lm(terms, State(state.poses, points), held, c.fine, name)
        return state, terms, report


def _segmentation_error(problem: JointProblem, state: State, terms: list[Term]
                        ) -> SharedError | None:
    """The plan's bone segmentation error as an error shared by the bone's edge points
    (none for an exact mesh, or for methods without edge points).

    A segmentation error moves the surface smoothly: points on the same stretch of bone are
    off alike, which no independent per-point sigma can say (it averages away over a
    thousand points). Its covariance between two points is ``sd^2 exp(-d^2 / 2 l^2)`` for
    their distance ``d`` (``l``, ``SolverConfig.segmentation_correlation_mm``), whitened by
    the bone's per-point ``sigma_mm``."""
    sd_mm = problem.plan.segmentation_sd_mm
    bone = [t for t in terms if isinstance(t, BackProjectionTerm) and t.body is None]
    if sd_mm <= 0.0 or not bone:
        return None
    c = problem.config
    points = state.points[np.concatenate([t.point_ids for t in bone])]
    # Points a fraction of the correlation length apart share one error (the cells'
    # centroids carry it), so that its cost grows with the bone's size, not its points'.
    cells = np.floor(points / (c.segmentation_correlation_mm / 3.0)).astype(np.int64)
    _, group = np.unique(cells, axis=0, return_inverse=True)
    group = group.reshape(-1)
    counts = np.bincount(group)
    centroids = np.stack([np.bincount(group, points[:, i]) for i in range(3)], axis=1) / counts[:, None]
    squared = np.sum((centroids[:, None, :] - centroids[None, :, :]) ** 2, axis=2)
    correlation = np.exp(-squared / (2.0 * c.segmentation_correlation_mm**2))
    return SharedError(bone, group, (sd_mm / c.sigma_mm) ** 2 * correlation)


def solve_joint(
    plan: Plan,
    views: list[ViewObservation],
    initial: InitialGuess,
    config: SolverConfig = SolverConfig(),
    callback: Callable[[str, IterationInfo], None] | None = None,
) -> SolveOutcome:
    """Estimate view and pin poses jointly and measure the resection plane.

    The solve starts from the encoders' guess. If it ends in a wrong basin (the outlines do
    not fit, or it does not converge), the patient set-up error is searched for globally
    (:mod:`solver.setup_search`), over wider ranges in turn, and the solve is run again from
    there."""
    start = time.perf_counter()
    problem = JointProblem(plan, views, config)
    poses = tuple(initial.T_cam_tibia) + tuple(initial.T_tibia_pin)
    refusal = gates.input_refusal(problem, initial)
    if refusal is not None:
        return _refused(problem, refusal, None, None, {}, start, poses)
    outcome = _solve_restarting(problem, initial, callback, start)
    if outcome.status != "measured" or not outcome.unclear_naming:
        return outcome
    # The pins' names were left open by their sightings at the bone's poses. At the poses
    # solved they may be clear (a wrong naming never was on the simulated cases, where the
    # other naming met better); if not, the other naming decides by fit.
    unclear = outcome.unclear_naming
    named = [swap_pins(v) if v.view_id in outcome.renamed else v for v in views]
    # The other naming: the one solved, with the open views' names swapped.
    other_views = [swap_pins(v) if v.view_id in unclear else v for v in named]
    length = plan.pin_length()
    if naming_clear(naming_score(named, outcome.T_cam_tibia, length),
                    naming_score(other_views, outcome.T_cam_tibia, length)):
        outcome.unclear_naming = []
        return outcome
    # From the views the first solve found (the bone's fit does not depend on the pins'
    # names), and without the global searches: astray, this naming simply does not measure.
    other = _solve_from(JointProblem(plan, other_views, config, naming_fixed=True), initial,
                        tuple(outcome.T_cam_tibia) + tuple(initial.T_tibia_pin), callback, start)
    chosen, refusal = settle_naming(outcome, other, unclear)
    log.info("views %s: pin names open; swapped they %s (%s)", unclear,
             "fit better" if chosen is other else "fit no better", other.status)
    if chosen is other:  # its names, as against the views given
        other.renamed = [v.view_id for v, given in zip(other_views, views) if v is not given]
    chosen.unclear_naming = unclear
    chosen.iterations = outcome.iterations + other.iterations
    if refusal is not None:
        chosen.status, chosen.reason = "not_measured", refusal
    return chosen


def _solve_restarting(problem: JointProblem, initial: InitialGuess,
                      callback: Callable[[str, IterationInfo], None] | None,
                      start: float) -> SolveOutcome:
    """A solve from the encoders' guess, restarted from the global set-up searches in turn
    while it goes astray."""
    poses = tuple(initial.T_cam_tibia) + tuple(initial.T_tibia_pin)
    outcome = _solve_from(problem, initial, poses, callback, start)
    iterations = outcome.iterations
    observed = [(T, view.camera, view.distance_map("bone"), view.contours["bone"])
                for T, view in zip(initial.T_cam_tibia, problem.views)]
    for search in problem.config.global_searches:
        if not outcome.went_astray:
            break
        correction = search_setup(problem.bone.coarse_contour, observed,
                                  problem.plan.landmarks.T_tibia_anat(), search)
        searched = tuple(T @ correction for T in initial.T_cam_tibia) + tuple(initial.T_tibia_pin)
        outcome = _solve_from(problem, initial, searched, callback, start)
        outcome.initialisation = "global set-up search"
        iterations += outcome.iterations
        outcome.iterations = iterations
    return outcome


def _refused(problem: JointProblem, reason: str, state: State | None,
             report: SolveReport | None, rms: dict[str, float], start: float,
             poses: tuple[Pose, ...] = (), went_astray: bool = False) -> SolveOutcome:
    """A "not_measured" outcome; ``poses`` stand in for the state when none was solved;
    ``went_astray`` says a restart from a global search may still measure."""
    n = problem.n_views
    final = state.poses if state is not None else poses
    return SolveOutcome(
        "not_measured", reason, state, list(final[:n]),
        list(final[n:]), None, None, rms, report.term_costs if report else {},
        report.iterations if report else 0, time.perf_counter() - start,
        bool(report and report.converged), report.reason if report else "not run",
        problem.point_counts(), went_astray=went_astray)


def _solve_from(problem: JointProblem, initial: InitialGuess, poses: tuple[Pose, ...],
                callback: Callable[[str, IterationInfo], None] | None,
                start: float) -> SolveOutcome:
    """One solve of the configured method from ``poses``, with its gates and uncertainty."""
    n = problem.n_views
    # Global step, shared by every method: where in each image is the bone? The views are
    # searched in parallel threads (OpenCV's template correlation releases the GIL), each
    # also building its pins' distance maps there (OpenCV's distance transform releases it
    # too: 10-20 ms each, which the later stages would otherwise build one after another).
    def aligned(T: Pose, view: ViewObservation) -> Pose:
        for label in PIN_LABELS:
            view.distance_map(label)
        return align_view_in_image(problem.bone.contour, T, view.camera, view.distance_map("bone"))

    with ThreadPoolExecutor(n) as pool:
        poses = tuple(pool.map(aligned, poses[:n], problem.views)) + poses[n:]
    schedule = _Schedule(problem, initial, callback)
    state, terms, fine = schedule.run(problem.config.method, State(poses, np.zeros((0, 3))))
    report = SolveReport(fine.converged, fine.reason, schedule.iterations, fine.cost,
                         fine.term_costs, schedule.seconds, fine.history)
    attributed = schedule.problem  # with the foreign edges dropped
    outcome = _judged(attributed, state, terms, fine, report, start)
    # The contour points offered (as extracted), and those that kept an edge point.
    outcome.point_counts = problem.point_counts()
    outcome.edge_point_counts = attributed.named(attributed.edge_point_counts(terms))
    outcome.renamed, outcome.unclear_naming = schedule.renamed, schedule.unclear_naming
    return outcome


def _judged(problem: JointProblem, state: State, terms: list[Term], fine: SolveReport,
            report: SolveReport, start: float) -> SolveOutcome:
    """The outcome of a finished solve: its quality gates, then the plane and its
    covariance-based uncertainty."""
    config, plan, n = problem.config, problem.plan, problem.n_views
    fixed = problem.fixed_dofs()
    rms, n_residuals = gates.residual_rms(terms, state)
    if not fine.converged:
        return _refused(problem, f"the solve did not converge ({fine.reason})", state, report,
                        rms, start, went_astray=True)
    misfit = (gates.contour_misfit(problem, state, terms, rms)
              or gates.pin_divergence(problem, state)
              or gates.odometry_misfit(rms, config.max_odometry_rms_sigma))
    if misfit is not None:
        return _refused(problem, misfit, state, report, rms, start, went_astray=True)
    final_views = list(state.poses[:n])
    separation = gates.view_separation_deg(final_views)
    if separation < config.min_view_separation_deg:
        return _refused(problem, f"views are too close in angle ({separation:.1f} deg apart)",
                        state, report, rms, start)

    pins = list(state.poses[n:])
    plane = fit_resection_plane(pins, plan.pin_length(), plan.landmarks)
    # E_mp charges the same contour pixels again that the edge points (E_rp, E_bp) explain:
    # where those exist, its information would be counted twice, and the spread understated.
    with_edges = any(term.name == "E_rp" for term in terms)
    cov_terms = [t for t in terms if not (with_edges and t.name == "E_mp")]
    cov, cov_segmentation = pose_covariance(cov_terms, state, fixed,
                                            _segmentation_error(problem, state, cov_terms))
    pin_slice = slice(6 * n, 6 * (n + 2))
    dof = n_residuals - len(state.points) * 3 - int(np.count_nonzero(~fixed))
    variance_factor = max(1.0, fine.cost / max(dof, 1))
    angle_cov = angle_covariance(
        pins, (cov * variance_factor + cov_segmentation)[pin_slice, pin_slice],
        plan.pin_length(), plan.landmarks)
    sigma_deg = np.degrees(np.sqrt(np.diag(angle_cov)))
    outcome = SolveOutcome("measured", "", state, final_views, pins, plane, angle_cov, rms,
                           fine.term_costs, report.iterations, time.perf_counter() - start,
                           True, fine.reason, problem.point_counts())
    if np.max(sigma_deg) > config.max_angle_sigma_deg:
        outcome.status = "not_measured"
        outcome.reason = (f"geometry is degenerate: angle uncertainty {np.max(sigma_deg):.2f} deg "
                          f"exceeds {config.max_angle_sigma_deg:.1f} deg")
    return outcome
