"""One solve's problem: its variables (view and pin poses, edge points), the observed
contour pixels, and the energy terms built from them (docs/solver.md)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np

from slamtka.solver.geometry import Pose
from slamtka.solver.kernels import nearest_points
from slamtka.solver.observations import LABELS, PIN_LABELS, ViewObservation, VisibleRegion
from slamtka.solver.optimizer import NoiseModel, RobustLoss, Term
from slamtka.solver.pin_naming import naming_clear, naming_score, swap_pays, swap_pins
from slamtka.solver.plan import Plan, RigidModel
from slamtka.solver.ray_seating import seat_on_rays
from slamtka.solver.solver_config import SolverConfig
from slamtka.solver.terms import (
    BackProjectionTerm,
    ModelProjectionTerm,
    RelativePoseTerm,
    ReprojectionTerm,
    pose_in_view,
)
from slamtka.solver.triangulation import PinSighting, triangulate_pin
from slamtka.solver.variables import PoseKey, body_key, pin_key, view_key

__all__ = ["EXPLAINED_PIN_EDGE_PX", "EdgeGroup", "InitialGuess", "JointProblem", "named_poses",
           "thin_contour"]

# Edge points' robust loss (in sigmas): a stray point pulls with a constant force.
_EDGE_LOSS = RobustLoss("huber", 2.0)
# A pin edge this close (px) to a fitted pin's outline is that pin's (a right fit's shared
# bar lies within 2.4 px of its pins at the 95th percentile).
EXPLAINED_PIN_EDGE_PX = 3.0


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


def named_poses(T_cam_tibia: Sequence[Pose], T_tibia_pin: Sequence[Pose]) -> dict[PoseKey, Pose]:
    """The views' poses (in view order) and the pins' (in ``PIN_LABELS`` order) by key."""
    return ({view_key(k): T for k, T in enumerate(T_cam_tibia)}
            | {pin_key(label): T for label, T in zip(PIN_LABELS, T_tibia_pin)})


def thin_contour(pixels: np.ndarray, spacing_px: float) -> np.ndarray:
    """Keep one observed edge pixel per ``spacing_px`` grid cell (order preserved)."""
    if len(pixels) == 0:
        return pixels
    cells = np.floor(pixels / spacing_px).astype(np.int64)
    cells -= cells.min(axis=0)
    # One integer per cell (rows are unique in 1-D ten times faster than along an axis).
    _, first = np.unique(cells[:, 0] * (cells[:, 1].max() + 1) + cells[:, 1], return_index=True)
    return pixels[np.sort(first)]



def _grown(mask: np.ndarray, by_px: float) -> np.ndarray:
    """The uint8 ``mask`` grown by ``by_px`` (a square of side 2 by_px + 1), as bools."""
    side = 2 * int(np.ceil(by_px)) + 1
    return cv2.dilate(mask, np.ones((side, side), np.uint8)) > 0


def _nearest_distances(points: np.ndarray, pixels: np.ndarray, cell_px: float) -> np.ndarray:
    """Each of ``pixels``' (M, 2) distance to the nearest of ``points`` (N >= 1, 2), exact
    (the compiled search, binned in cells of ``cell_px``)."""
    gap = points[nearest_points(points, np.ascontiguousarray(pixels, dtype=float), cell_px)] - pixels
    return np.sqrt(gap[:, 0] ** 2 + gap[:, 1] ** 2)


def _within(a: np.ndarray, b: np.ndarray, gap_px: float) -> bool:
    """Whether two uint8 masks come within ``gap_px`` of each other (or overlap)."""
    return bool(np.any(_grown(a, gap_px) & (b > 0)))


class EdgeGroup(NamedTuple):
    """The edge points of one model in one view: their ids among the state's points, the
    contour pixels they were seated from and their rays' directions (model frame)."""

    ids: np.ndarray
    pixels: np.ndarray
    directions: np.ndarray


class JointProblem:
    """Variables, terms and gauge of one solve, built from a plan and the views."""

    def __init__(self, plan: Plan, views: list[ViewObservation], config: SolverConfig,
                 naming_fixed: bool = False, edges_sought: bool = False):
        """``naming_fixed``: take the views' pin names as given (no :meth:`relabelled`);
        ``edges_sought``: the bone contours were found near the model's outline
        (:meth:`with_bone_edges_sought`), so its fit to them proves less."""
        self.plan, self.views, self.config = plan, list(views), config
        self.naming_fixed, self.edges_sought = naming_fixed, edges_sought
        self.bone = plan.bone_model()
        self.pin = plan.pin_model()
        # The pose variables: each view's camera, then each pin (the bone is the reference).
        self.view_keys = tuple(view_key(k) for k in range(len(views)))
        self.pin_keys = tuple(pin_key(label) for label in PIN_LABELS)
        self.pixels = {(k, label): thin_contour(v.contours[label], config.sampling.edge_spacing_px)
                       for k, v in enumerate(views) for label in LABELS}
        # ... and more sparsely for the coarse silhouette stages (SamplingConfig.coarse_thinning).
        self.coarse_pixels = {key: thin_contour(px, config.sampling.edge_spacing_px * config.sampling.coarse_thinning)
                              for key, px in self.pixels.items()}

    def attributed(self, poses: Mapping[PoseKey, Pose], labels: tuple[str, ...]) -> JointProblem:
        """The problem without the contour pixels of ``labels`` that no part of their
        models' outlines, traced at ``poses``, comes near (``SamplingConfig.foreign_edge_px``):
        the edges of a femur, a patella, a retractor or a collimator blade that extraction
        could not tell from the tibia's, or a halo beside the pins taken for a pin's (a
        pixel near the other pin is a naming question, not a foreign edge: kept). Only
        contours whose own model's outline lies on them (median ``max_coarse_bone_median_px``
        over its visible part) are pruned: a model off its contour says nothing about which
        edges are its own. ``self`` when nothing is dropped."""
        c = self.config
        reach = c.sampling.foreign_edge_px
        if reach is None:
            return self
        views = list(self.views)
        for k, view in enumerate(self.views):
            outlines = {label: self._outline_px(k, label, poses) for label in labels}
            if not any(len(uv) for uv in outlines.values()):
                continue
            nearby = np.vstack([uv for uv in outlines.values() if len(uv)])
            kept = {}
            for label in labels:
                pixels, uv = view.contours[label], outlines[label]
                if label == "bone" and view.bone_visible is not None:
                    uv = uv[view.bone_visible.contains(uv)]
                if len(pixels) == 0 or len(uv) == 0 or float(np.median(
                        view.distance_map(label).query(uv)[0])) > c.gates.max_coarse_bone_median_px:
                    continue
                near = _nearest_distances(nearby, pixels, reach) <= reach
                if not near.all():
                    kept[label] = pixels[near]
            if kept:
                views[k] = view.with_contours(**kept)
        if all(a is b for a, b in zip(views, self.views)):
            return self
        return JointProblem(self.plan, views, c, self.naming_fixed, self.edges_sought)

    def bone_edges_sought(self, poses: Mapping[PoseKey, Pose], k: int, reach_px: float
                          ) -> tuple[np.ndarray, float]:
        """The edges view ``k``'s frame shows within ``reach_px`` of the bone model's
        outline at ``poses``, and the share of its visible outline that found one (the
        view's :class:`EdgeSearch`, which it must have)."""
        view = self.views[k]
        assert view.bone_edge_search is not None
        footprint = self.bone.contour.footprint(self.T_cam_body(poses, k, "bone"), view.camera, 1)
        return view.bone_edge_search(footprint, reach_px)

    def with_bone_edges_sought(self, poses: Mapping[PoseKey, Pose], reach_px: float) -> JointProblem:
        """The problem with each view's bone contour replaced by the edges its frame shows
        within ``reach_px`` of the bone model's outline at ``poses`` (views without an edge
        search keep theirs)."""
        views = [view.with_contours(bone=self.bone_edges_sought(poses, k, reach_px)[0])
                 if view.bone_edge_search is not None else view for k, view in enumerate(self.views)]
        return JointProblem(self.plan, views, self.config, self.naming_fixed, edges_sought=True)

    def with_pin_edges_shared(self, poses: Mapping[PoseKey, Pose]) -> tuple[JointProblem, list[str]]:
        """The problem with the pin edges of each view where the two pins' shadows lie on
        each other (``SamplingConfig.shared_pin_shadow_gap_px``) shared out by the fit, and
        the ids of those views: where ``SamplingConfig.share_pin_edges`` asks, and always in
        a view whose edges are pooled already (the extraction gave both pins one bar). Only
        views whose pins are opaque (:attr:`ViewObservation.pins_opaque`) are shared out:
        contours drawn pin by pin name each pin's edges already.

        Seen one behind the other, the pins cast one bar, and the extraction's split of its
        edges into two pins is a guess (idealised seed 12 was split about 150 px from where
        one pin ends). Yet the bar still says where both
        pins are: each of its edges is one pin's or the other's. So each edge pixel (as
        extracted, both names pooled) goes to the pin whose outline at ``poses`` passes
        nearer, none to either where the two pass about as near; a pin's outline under the
        other pin's shadow has no edge to lie on and is not charged. A view shared once
        stays shared, its edges shared out again at each call."""
        views, shared = list(self.views), list[str]()
        for k, view in enumerate(self.views):
            if view.pin_edges is None and not self.config.sampling.share_pin_edges:
                continue
            shadows = self._pin_shadows(k, poses) if view.pins_opaque else None
            if shadows is None or (view.pin_edges is None and not self._touching(shadows)):
                continue
            edges = view.pin_edges
            if edges is None:
                edges = np.vstack([view.contours[label] for label in PIN_LABELS])
            views[k] = replace(view.with_contours(**self._shared_out(k, edges, poses)), pin_edges=edges,
                               pins_visible=self._outside_other_shadow(shadows))
            shared.append(view.view_id)
        if not shared:
            return self, []
        return JointProblem(self.plan, views, self.config, self.naming_fixed, self.edges_sought), shared

    def unexplained_pin_edge_share(self, k: int, poses: Mapping[PoseKey, Pose]) -> float:
        """The share of view ``k``'s pooled pin edges (a view shared out) farther than
        :data:`EXPLAINED_PIN_EDGE_PX` from both pins' outlines at ``poses``: a part of the
        bar the fitted pins do not account for (0 for a view not shared out)."""
        edges = self.views[k].pin_edges
        if edges is None or not len(edges):
            return 0.0  # not shared out: no outline is traced for it
        outlines = [self._outline_px(k, label, poses) for label in PIN_LABELS]
        if not any(len(o) for o in outlines):
            return 0.0
        distances = _nearest_distances(np.vstack(outlines), edges, 8.0)
        return float(np.mean(distances > EXPLAINED_PIN_EDGE_PX))

    def pins_touch(self, poses: Mapping[PoseKey, Pose]) -> bool:
        """Whether the two pins' shadows touch at ``poses`` in some view of opaque pins
        (within ``SamplingConfig.shared_pin_shadow_gap_px``)."""
        return any(view.pins_opaque and self._touching(self._pin_shadows(k, poses))
                   for k, view in enumerate(self.views))

    def _pin_shadows(self, k: int, poses: Mapping[PoseKey, Pose]) -> list[np.ndarray]:
        """Each pin's projection in view ``k`` at ``poses`` (uint8 masks, full resolution)."""
        return [self.pin.contour.footprint(self.T_cam_body(poses, k, label), self.views[k].camera, 1)
                for label in PIN_LABELS]

    def _touching(self, shadows: list[np.ndarray]) -> bool:
        return _within(shadows[0], shadows[1], self.config.sampling.shared_pin_shadow_gap_px)

    def _shared_out(self, k: int, edges: np.ndarray, poses: Mapping[PoseKey, Pose]) -> dict[str, np.ndarray]:
        """View ``k``'s pin edge pixels by the pin whose outline at ``poses`` is nearer."""
        distances = []
        for label in PIN_LABELS:
            outline = self._outline_px(k, label, poses)
            distances.append(_nearest_distances(outline, edges, 8.0) if len(outline) and len(edges)
                             else np.full(len(edges), np.inf))
        to_first, to_second = distances
        with np.errstate(invalid="ignore"):  # both outlines empty (pins off the frame): neither
            clear = np.abs(to_first - to_second) >= self.config.sampling.pin_edge_ambiguity_px
        return {"pin1": edges[clear & (to_first < to_second)], "pin2": edges[clear & (to_second < to_first)]}

    @staticmethod
    def _outside_other_shadow(shadows: list[np.ndarray]) -> dict[str, VisibleRegion]:
        """Where each pin's own edge can be seen: outside the other pin's shadow (uint8
        masks), grown by a pixel (an outline along the other's edge is that edge's as much
        as its own)."""
        grown = [_grown(shadow, 1.0) for shadow in shadows]
        return {"pin1": VisibleRegion(~grown[1], 1), "pin2": VisibleRegion(~grown[0], 1)}

    def _outline_px(self, k: int, label: str, poses: Mapping[PoseKey, Pose]) -> np.ndarray:
        """Pixels (N, 2) of the outline of ``label``'s model in view ``k`` at ``poses``."""
        view, T = self.views[k], self.T_cam_body(poses, k, label)
        outline = self.model(label).contour.outline_points(
            T, view.camera, self.config.sampling.silhouette_spacing_px, outer_only=label == "bone")
        return view.camera.project(T.apply(outline)) if len(outline) else np.zeros((0, 2))

    def point_counts(self) -> dict[str, int]:
        """Kept contour points per view and label, for the result document."""
        return self.named({key: len(px) for key, px in self.pixels.items()})

    def named(self, counts: dict[tuple[int, str], int]) -> dict[str, int]:
        """Counts per (view index, label) keyed as the result document names them."""
        return {f"{self.views[k].view_id}/{label}": n for (k, label), n in counts.items()}

    def edge_point_counts(self, terms: list[Term]) -> dict[tuple[int, str], int]:
        """Contour points per view and label that kept an edge point in ``terms`` (those of
        the re-projection terms; empty for methods without edge points)."""
        return {(t.view.position, t.body.label): len(t.pixels)
                for t in terms if isinstance(t, ReprojectionTerm)}

    def model(self, label: str) -> RigidModel:
        return self.bone if label == "bone" else self.pin

    def fixed_dofs(self, views: bool = False, pins: bool = False) -> dict[PoseKey, np.ndarray]:
        """Per pose, the parameters held fixed: always each pin's roll about its own axis (a
        gauge direction), and optionally all view or all pin parameters (staged solves)."""
        return ({key: np.full(6, views) for key in self.view_keys}
                | {key: np.array([pins] * 5 + [True]) for key in self.pin_keys})

    def T_cam_body(self, poses: Mapping[PoseKey, Pose], k: int, label: str) -> Pose:
        """The pose of ``label``'s model in view ``k``'s camera."""
        return pose_in_view(poses, view_key(k), body_key(label))

    def relabelled(self, poses: Mapping[PoseKey, Pose]) -> tuple[JointProblem, list[str], list[str]]:
        """The problem with the two pins' names swapped in each view where the swap makes
        both pins' sightings meet clearly better (views posed from the bone alone; names
        from extraction's guess; :mod:`solver.pin_naming`). Also the ids of the views
        swapped, and of those whose naming is not clear either way."""
        if self.naming_fixed:
            return self, [], []
        length, view_poses = self.plan.pin_length(), [poses[key] for key in self.view_keys]
        views, swapped, unclear = list(self.views), list[str](), list[str]()
        for k in range(1, len(views)):
            trial = views[:k] + [swap_pins(views[k])] + views[k + 1:]
            kept, changed = naming_score(views, view_poses, length), naming_score(trial, view_poses, length)
            if swap_pays(kept, changed):
                views, swapped, kept, changed = trial, swapped + [views[k].view_id], changed, kept
            if not naming_clear(kept, changed):
                unclear.append(views[k].view_id)
        problem = JointProblem(self.plan, views, self.config, edges_sought=self.edges_sought) if swapped else self
        return problem, swapped, unclear

    def triangulated_pins(self, poses: Mapping[PoseKey, Pose]) -> dict[PoseKey, Pose]:
        """Each pin's pose triangulated from its contours in the views at ``poses`` (the
        current pin pose where it cannot be)."""
        pins = {}
        for key in self.pin_keys:
            current = poses[key]
            sightings = [PinSighting(view.camera, poses[view_key(k)], self.pixels[k, key.label])
                         for k, view in enumerate(self.views)]
            pins[key] = triangulate_pin(sightings, current, self.plan.pin_length()) or current
        return pins

    def seated_points(self, poses: Mapping[PoseKey, Pose], labels: tuple[str, ...] = LABELS
                      ) -> tuple[np.ndarray, dict[tuple[int, str], EdgeGroup]]:
        """Edge points of ``labels`` seated on their rays for ``poses``, and per view and
        label the group of points kept: for the bone, those whose rays pass within
        ``SamplingConfig.max_ray_miss_mm`` of it."""
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
                kept = np.abs(model.sdf.query(seated, gradient=False)[0]) <= self.config.sampling.max_ray_miss_mm
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
                         thinned: bool = False) -> list[ModelProjectionTerm]:
        """E_mp of ``labels`` in every view; ``light`` traces the bone's lighter mesh (the
        set-up search's), enough under a wide robust scale (a pin's mesh is light already);
        ``thinned`` samples contours and outlines ``SamplingConfig.coarse_thinning`` times
        more sparsely."""
        c = self.config
        thinning = c.sampling.coarse_thinning if thinned else 1.0
        terms: list[ModelProjectionTerm] = []
        for k, view in enumerate(self.views):
            for label in labels:
                if len(view.contours[label]) == 0:
                    continue
                terms.append(ModelProjectionTerm(
                    "E_mp", view_key(k), body_key(label), view.camera,
                    (self.bone.coarse_contour if light and label == "bone"
                     else self.model(label).contour),
                    view.distance_map(label),
                    (self.coarse_pixels if thinned else self.pixels)[k, label],
                    NoiseModel(c.noise.sigma_px, loss, weight),
                    c.sampling.silhouette_spacing_px * thinning,
                    outer_only=(label == "bone"), freeze_outline=freeze_outline,
                    visible=view.bone_visible if label == "bone" else
                    (view.pins_visible or {}).get(label)))
        return terms

    def odometry_terms(self, initial: InitialGuess) -> list[Term]:
        """E_odo between the first view and each other one, if the encoders measured it
        (whether a method uses it is its schedule's choice)."""
        if initial.odometry_sigma is None:
            return []
        sigma_rad, sigma_mm = initial.odometry_sigma
        anchor = self.plan.landmarks.T_tibia_anat()
        first = initial.T_cam_tibia[0]
        noise = NoiseModel((sigma_mm,) * 3 + (sigma_rad,) * 3)
        return [RelativePoseTerm("E_odo", view_key(0), view_key(k), T @ first.inverse(), anchor, noise)
                for k, T in enumerate(initial.T_cam_tibia) if k > 0]

    def edge_terms(self, points: np.ndarray, groups: dict[tuple[int, str], EdgeGroup]
                   ) -> list[Term]:
        """E_rp and E_bp of the edge points ``points`` seated by :meth:`seated_points`."""
        c = self.config.noise
        terms: list[Term] = []
        for (k, label), group in groups.items():
            terms.append(ReprojectionTerm("E_rp", view_key(k), body_key(label), self.views[k].camera,
                                          group.pixels, group.ids,
                                          NoiseModel(c.sigma_px, _EDGE_LOSS, c.w_rp)))
            sigma_mm = c.sigma_mm if label == "bone" else c.pin_sigma_mm
            terms.append(BackProjectionTerm(
                "E_bp", self.model(label).sdf, group.ids, group.directions, points[group.ids],
                NoiseModel((sigma_mm, c.sigma_depth_mm), _EDGE_LOSS, c.w_bp), view=view_key(k),
                body=body_key(label)))
        return terms

