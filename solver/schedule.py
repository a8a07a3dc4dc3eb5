"""The stage schedule of each method, as data: one table of stages per method, run in
order by :class:`slamtka.solver.stages.StageRunner`. A new baseline is a new entry of
``SCHEDULES``.

The proposed method (``slam``): each view on the bone's silhouette (an annealed robust
scale, tied together by the encoders' relative motion E_odo), the pins triangulated from
the ends of their contours and refined, every silhouette at once, then the joint energy
with edge points seated where their rays graze the models (seated again while a stage still
turns the poses). ``slam-noenc`` is the same without E_odo; the paper's four baselines use
model projection only (E_mp) or contour back-projection only (E_rp + E_bp), each "split"
(views from the bone first, then the pins with the views held) or "joint".
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Literal

from slamtka.solver.observations import LABELS, PIN_LABELS

__all__ = ["METHODS", "SCHEDULES", "Held", "MethodSchedule", "Stage", "Step"]


class Step(Enum):
    """What a stage does."""

    # Views on the bone's silhouette under each of ``ScheduleConfig.coarse_loss_scales``;
    # then foreign bone edges dropped, a bone still off its contours stops the solve (gone
    # astray), and pin labels swapped in views where that makes the pins' sightings meet.
    BONE_SILHOUETTE = "bone silhouette"
    TRIANGULATE_PINS = "pins triangulated"  # each pin from the ends of its contours
    SILHOUETTES = "silhouettes"  # E_mp of the stage's labels
    EDGES = "edge points"  # E_rp + E_bp of edge points seated on their rays
    JOINT = "joint"  # edge points + E_mp, the points seated again while the poses turn


class Held(Enum):
    """Which poses a stage holds fixed (besides each pin's unobservable roll)."""

    NOTHING = "nothing"
    VIEWS = "views"
    PINS = "pins"


Budget = Literal["coarse", "coarse_pins", "coarse_all", "fine"]


@dataclass(frozen=True)
class Stage:
    """One row of a method's schedule. ``budget`` names the ``ScheduleConfig`` options the
    optimiser runs with; a stage without one only sets the energy the solve is judged by."""

    step: Step
    name: str = ""  # as the iteration callback and the reports name it
    labels: tuple[str, ...] = LABELS
    held: Held = Held.NOTHING
    budget: Budget | None = "fine"
    thinned: bool = False  # contours and outlines sampled sparsely (SamplingConfig.coarse_thinning)
    odometry: bool = False  # with E_odo, where the method uses it
    # After the stage, contour pixels of its labels that no part of the posed models'
    # outlines comes near are dropped (SamplingConfig.foreign_edge_px).
    attributed: bool = False


@dataclass(frozen=True)
class MethodSchedule:
    """A method's stages, and whether it keeps the encoders' motion as a factor (E_odo)."""

    stages: tuple[Stage, ...]
    odometry: bool = False


_BONE = Stage(Step.BONE_SILHOUETTE, "coarse bone", ("bone",), Held.PINS, "coarse", thinned=True,
              odometry=True, attributed=True)
_PINS = Stage(Step.TRIANGULATE_PINS, budget=None)
_COARSE_PINS = Stage(Step.SILHOUETTES, "coarse pins", PIN_LABELS, Held.VIEWS, "coarse_pins",
                     attributed=True)
_SLAM = (
    _BONE, _PINS, _COARSE_PINS,
    Stage(Step.SILHOUETTES, "coarse all", budget="coarse_all", thinned=True, odometry=True),
    Stage(Step.JOINT, "joint", odometry=True),
)

SCHEDULES: dict[str, MethodSchedule] = {
    "slam": MethodSchedule(_SLAM, odometry=True),
    "slam-noenc": MethodSchedule(_SLAM),
    "projection-split": MethodSchedule((
        _BONE, _PINS,
        Stage(Step.SILHOUETTES, "coarse pins", PIN_LABELS, Held.VIEWS),
        Stage(Step.SILHOUETTES, "every silhouette", budget=None),
    )),
    "projection-joint": MethodSchedule((
        _BONE, _PINS, _COARSE_PINS,
        Stage(Step.SILHOUETTES, "projection joint"),
    )),
    "backprojection-split": MethodSchedule((
        Stage(Step.EDGES, "back-projection views", ("bone",), Held.PINS),
        _PINS,
        Stage(Step.EDGES, "back-projection pins", held=Held.VIEWS),
    )),
    "backprojection-joint": MethodSchedule((
        _PINS,
        Stage(Step.EDGES, "back-projection joint"),
    )),
}

METHODS = tuple(SCHEDULES)
