"""The solver's settings, split by kind: noise model, contour sampling, stage schedule,
quality-gate limits and the global search. ``SolverConfig()`` is the tuned default; the
evidence behind each figure is in ``docs/decisions/``."""

from __future__ import annotations

from dataclasses import dataclass, field

from slamtka.solver.optimizer import LMOptions
from slamtka.solver.schedule import METHODS
from slamtka.solver.setup_search import SetupSearch

__all__ = ["GateLimits", "NoiseModelConfig", "SamplingConfig", "ScheduleConfig",
           "SolverConfig"]


@dataclass(frozen=True)
class NoiseModelConfig:
    """Expected noise (sigmas) and weights of the energy terms
    (docs/decisions/2026-12-05-noise-model.md)."""

    sigma_px: float = 2.0  # contour noise, pixels
    sigma_mm: float = 0.5  # a true bone edge point's distance to the bone's surface
    pin_sigma_mm: float = 0.1  # ... and to a pin's (a machined part)
    segmentation_correlation_mm: float = 10.0  # distance over which segmentation error stays alike
    sigma_depth_mm: float = 0.5  # an edge point's depth along its ray from where it grazes
    w_rp: float = 1.0
    w_bp: float = 1.0
    w_mp: float = 0.1


@dataclass(frozen=True)
class SamplingConfig:
    """Which contour pixels become edge points and silhouette samples
    (docs/decisions/2026-12-05-edge-points.md)."""

    edge_spacing_px: float = 6.0  # observed contours are thinned to this spacing
    silhouette_spacing_px: float = 5.0
    coarse_thinning: float = 2.0  # coarse stages sample this many times more sparsely
    max_ray_miss_mm: float = 3.0  # a bone pixel whose ray misses the bone by more: no edge point
    foreign_edge_px: float | None = 15.0  # bone pixels this far from the outline: another body's
    # Whether the pin edges of a view where the two pins' shadows come within this many px
    # are shared out between the pins by the fit (set by solve_joint when a solve refused
    # over the pins is tried again); an edge whose distances to the two pins' outlines
    # differ by less (px) is neither's.
    share_pin_edges: bool = False
    shared_pin_shadow_gap_px: float = 2.0
    pin_edge_ambiguity_px: float = 1.0


@dataclass(frozen=True)
class ScheduleConfig:
    """Iteration budgets and stopping rules of the stages
    (docs/decisions/2026-12-05-stage-schedule.md)."""

    coarse: LMOptions = LMOptions(max_iterations=5, relative_tolerance=1e-3)
    coarse_pins: LMOptions = LMOptions(max_iterations=4, relative_tolerance=1e-3)
    coarse_loss_scales: tuple[float, ...] = (20.0, 6.0, 2.0)  # Cauchy scales, in sigmas
    light_mesh_min_scale: float = 10.0  # bone stages at this scale or wider trace the light mesh
    # A bone stage off its contour seeks the bone's edges again near the model's outline,
    # from this far out to this close (px), fitting the views to them each time.
    bone_edge_reach_px: tuple[float, ...] = (16.0, 8.0, 4.0)
    # A solve that found the bone but failed a fit gate seeks the bone's edges again near
    # its solved outline, this far and then this close (px), and is solved again each time.
    # Not from 16 px: interior edges that near (a fibula's, a plateau's rim) measured
    # scatter seed 29 1.1 deg off in STR.
    refit_edge_reach_px: tuple[float, ...] = (8.0, 4.0)
    coarse_all: LMOptions = LMOptions(max_iterations=10, relative_tolerance=1e-3)
    fine: LMOptions = LMOptions(max_iterations=60, relative_tolerance=5e-3, step_tolerance=1e-3,
                                min_lambda=1e-3)
    joint_seated_iterations: int = 3
    reseat_turn_deg: float = 0.1
    max_seatings: int = 5
    settled_angle_deg: float = 0.005


@dataclass(frozen=True)
class GateLimits:
    """Limits of the quality gates (docs/decisions/2026-12-05-quality-gates.md)."""

    min_view_separation_deg: float = 15.0
    min_bone_points: int = 50
    min_pin_points: int = 20
    max_stray_fraction: float = 0.2
    max_residual_rms_px: float = 4.0
    max_silhouette_median_px: float = 2.5
    max_pin_outline_p90_px: float = 60.0
    max_pin_graze_offset_mm: float = 0.8
    max_pin_divergence_deg: float = 3.0
    # Pins drilled through a cutting block on the front of the tibia run within some 20 deg
    # of its front-to-back axis (the simulator's: 17 deg at most); pins whose mean axis is
    # further from it than this are other steel (gates.pins_across_the_tibia).
    max_pin_from_anteroposterior_deg: float = 45.0
    # Beyond it, a turn within the pins' plane still passes up to this many of its standard
    # deviations: the views do not resolve it (gates.pin_divergence).
    max_unresolved_turn_sds: float = 4.0
    # Nor is a turn within the plane past this excused, whatever the views resolve: right
    # solves of pins seen edge-on left them 25-33 deg apart (surgeon's views seeds 16, 27),
    # a wrong one 66 deg, its plane 1.3 deg off (seed 14; docs/realism.md, 31st pass).
    max_excused_turn_deg: float = 45.0
    # A view whose source lies within this of the pins' plane sees it edge-on: where every
    # view does, in a solve held to the encoders' motion, nothing resolves the pins' turn
    # within that plane, nor does the plane depend on it (gates.edge_on_plane_confirmed).
    max_edge_on_elevation_deg: float = 1.5
    max_odometry_rms_sigma: float = 7.5
    max_coarse_bone_median_px: float = 4.0
    min_sought_edge_share: float = 0.5  # of the outline, where its edges were sought near it
    min_visible_outline_share: float = 0.4
    max_pin_overlap_share: float = 0.6
    # In a view whose pins' one bar the fit shared out: the share of its edges that may lie
    # off both fitted pins (EXPLAINED_PIN_EDGE_PX away; 0-1% where right, 7-11% with pin
    # heads on the bar, which no pin model has; 16-29% where wrong: a pin slid along its
    # axis and the views turned to make up for it, or a naming the other beat).
    max_unexplained_pin_edge_share: float = 0.14
    max_angle_sigma_deg: float = 2.0


def _default_searches() -> tuple[SetupSearch, ...]:
    """+-30, then +-60, then +-90 deg (docs/decisions/2026-12-05-global-search.md)."""
    return (SetupSearch(),
            SetupSearch(coarse_half_range_deg=60.0, coarse_step_deg=20.0, refinements=3),
            SetupSearch(coarse_half_range_deg=90.0, coarse_step_deg=30.0, refinements=4, rescored=16,
                        screened=48))


@dataclass(frozen=True)
class SolverConfig:
    """Everything a solve is configured by; ``method`` is one of ``METHODS``."""

    noise: NoiseModelConfig = NoiseModelConfig()
    sampling: SamplingConfig = SamplingConfig()
    schedule: ScheduleConfig = ScheduleConfig()
    gates: GateLimits = GateLimits()
    global_searches: tuple[SetupSearch, ...] = field(default_factory=_default_searches)
    method: str = "slam"  # one of METHODS, the keys of schedule.SCHEDULES

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
