"""Which pin is which in each view, and what to do when the images cannot say.

Extraction names the two pins in each view by its own guess. A pin called pin 1 in one view
and pin 2 in the other is fitted as two pins that cross between the views: with two views
any two image lines back-project to some 3-D line, so the wrong naming still fits, and it
tilts the plane about the pins' direction (7 deg on one simulated case). The views are first
put right by how well each pin's sightings meet (:func:`swap_pays`). Where the pins lie near
a plane through both X-ray sources their sightings meet about as well either way
(:func:`naming_clear` is false): the case is then solved under both namings and
:func:`settle_naming` keeps the one that fits clearly better, or the one plane both agree
on, and otherwise refuses, naming the views. Measured in docs/solver.md ("Pin naming").

The bone says it too: the pins are drilled into the tibia, and the wrong naming, whose
pins are where the other pins' sightings cross, puts a pin deeper or shallower in the
views' common plane, through the bone or in front of it (docs/solver.md, "Pin naming",
step 4).
"""

from __future__ import annotations

from typing import Protocol, TypeVar

import numpy as np

from slamtka.solver.geometry import Pose
from slamtka.solver.observations import PIN_LABELS, ViewObservation
from slamtka.solver.sdf import SignedDistanceField
from slamtka.solver.triangulation import PinSighting, sighting_score

__all__ = ["naming_score", "swap_pins", "swap_pays", "naming_clear", "cost_gap", "settle_naming",
           "pins_out_of_bone_mm", "NAMING_MIN_COST_GAP", "NAMING_PLANE_TOLERANCE_DEG"]

# A view's names are swapped when the swap at least halves how badly the pins' sightings
# meet and gains more than a millimetre; they are clear when the other naming is worse by
# as much.
_SWAP_GAIN = 0.5
_SWAP_MIN_MM = 1.0
# Of two solves under both namings (the same residuals, as many parameters), one whose final
# cost (sum of whitened squares) is lower by this much wins: a likelihood ratio of e^12.5.
# Wrong namings cost 110-1,300 more than the right one on 80 simulated cases (docs/solver.md,
# "Pin naming"). On frames the costs are compared in units of the fits' own dispersion
# (:func:`cost_gap`): a headed-pin case's wrong naming cost 91-112 less than the right one,
# most of it in the model-projection term, whose residuals were 2.1-2.4 sigma RMS under
# either naming (a headless pin model fitted to headed pins); it was measured 14.9 deg off
# at level 3. Closer than this, both namings must give the same plane within the
# tolerance, else there is no answer.
NAMING_MIN_COST_GAP = 100.0
# gates.Why.GATE_FAILED (the contours do not fit, the pins are not parallel): the kind of
# refusal of another naming that does not let the first stand (gates imports this module).
_ANSWER_GATE_FAILED = "gate_failed"
NAMING_PLANE_TOLERANCE_DEG = 0.5
# A pin is in the bone when its deeper end lies within this of the plan's bone surface (its
# segmentation and the fit's error along the pin: the right naming's pins are 1.7-14 mm
# inside on the simulated cases), and clearly out of it beyond the second figure (the wrong
# naming's farthest pin: 2.8-22 mm out).
_PIN_IN_BONE_MM = 1.0
PIN_OUT_OF_BONE_MM = 4.0


class _Solved(Protocol):
    """What :func:`settle_naming` reads of a solve's outcome."""

    status: str
    reason: str
    term_costs: dict[str, float]
    residual_rms: dict[str, float]  # per term, in units of its sigma

    @property
    def why(self) -> str | None: ...  # a refusal's kind (gates.Why, a str)

    @property
    def angles_deg(self) -> tuple[float, float] | None: ...


Solved = TypeVar("Solved", bound=_Solved)


def swap_pins(view: ViewObservation) -> ViewObservation:
    """The view with its two pins' names swapped."""
    swapped = view.with_contours(pin1=view.contours["pin2"], pin2=view.contours["pin1"])
    if view.pins_visible is not None:
        swapped.pins_visible = {"pin1": view.pins_visible["pin2"], "pin2": view.pins_visible["pin1"]}
    return swapped


def naming_score(views: list[ViewObservation], T_cam_tibia: list[Pose] | tuple[Pose, ...],
                 pin_length_mm: float) -> float:
    """How badly the pins' sightings meet under the views' names, at these view poses (mm;
    the sum over both pins, see :func:`solver.triangulation.sighting_score`)."""
    return sum(sighting_score([PinSighting(v.camera, T, v.contours[label])
                               for v, T in zip(views, T_cam_tibia)], pin_length_mm)
               for label in PIN_LABELS)


def swap_pays(kept_mm: float, swapped_mm: float) -> bool:
    """Whether swapping a view's names makes the pins' sightings meet clearly better."""
    return swapped_mm < min(_SWAP_GAIN * kept_mm, kept_mm - _SWAP_MIN_MM)


def naming_clear(chosen_mm: float, other_mm: float) -> bool:
    """Whether the naming chosen is clearly better than the other one (the swap rule the
    other way round); both infinite (a pin unseen) counts as clear: nothing to choose."""
    if not np.isfinite(chosen_mm):
        return True
    return swap_pays(other_mm, chosen_mm)


def cost_gap(first: _Solved, second: _Solved) -> float:
    """How much worse the second naming fits than the first (negative: better): the
    difference of their final costs, each energy term's share divided by that term's
    dispersion, the mean square of its whitened residuals in the naming that fits it better,
    where above 1 (a quasi-likelihood ratio). A model that misfits the image everywhere (a
    headless pin model over headed pins, a bone outline beside another bone's edge) inflates
    a term's cost under both namings alike; its raw difference would overstate the evidence
    for either by that factor. Residuals within their sigma leave the costs as they are."""
    gap = 0.0
    for term, cost in first.term_costs.items():
        rms = min(first.residual_rms.get(term, 1.0), second.residual_rms.get(term, 1.0))
        gap += (second.term_costs.get(term, 0.0) - cost) / max(1.0, rms * rms)
    return gap


def pins_out_of_bone_mm(T_tibia_pin: list[Pose], pin_length_mm: float,
                        bone: SignedDistanceField) -> float:
    """How far the pin farthest from the bone has its deeper end outside it (mm; negative:
    both pins reach into the bone). Either end may be the one drilled in: a pin's shadow
    hardly says which end is its trocar tip."""
    ends = np.array([T.apply(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, pin_length_mm]]))
                     for T in T_tibia_pin]).reshape(-1, 3)
    depth = bone.query(ends, gradient=False)[0].reshape(len(T_tibia_pin), 2)
    return float(np.max(np.min(depth, axis=1)))


def _bone_prefers(out_of_bone_mm: tuple[float, float] | None) -> int | None:
    """Which naming (0, 1) alone has both pins in the bone while the other has one clearly
    out of it, or None."""
    if out_of_bone_mm is None:
        return None
    for k in (0, 1):
        if out_of_bone_mm[k] <= _PIN_IN_BONE_MM and out_of_bone_mm[1 - k] >= PIN_OUT_OF_BONE_MM:
            return k
    return None


def settle_naming(first: Solved, second: Solved, views: list[str],
                  sightings_prefer_second: bool | None = None,
                  out_of_bone_mm: tuple[float, float] | None = None) -> tuple[Solved, str | None]:
    """Of two solves under the two namings of ``views``, the one to report, and the refusal
    when neither can be told right (None: the outcome returned stands as it is).

    Where only one naming has both pins in the bone (``out_of_bone_mm``, each naming's
    :func:`pins_out_of_bone_mm`), their place decides where the fit cannot tell: that
    naming's outcome stands, measured or refused. Where the fit clearly chose the other,
    the two disagree and nothing is measured. Otherwise the fit decides
    (:func:`_settle_by_fit`).

    A first naming not measured (its geometry degenerate: the angles too uncertain, as the
    wrong naming's are where its pins cross the views' common plane) gives way only to a
    measured other naming that the bone prefers. One refused because it does not fit (its
    outlines off their contours, its pins not parallel) gives way only where the other also
    fits clearly better and no worse to the encoders: the encoders witness the views
    independently of the names (scatter seed 16: the other naming, preferred by the bone
    and fitting better by 183, strained the encoders from 5.1 to 7.3 sigma and was measured
    1.07 deg off; idealised seed 2 at level 3: better by 700, 6.3 to 3.2 sigma, right).
    Solved without the encoders, such a first naming stands: no witness is left."""
    in_bone = _bone_prefers(out_of_bone_mm)
    if first.status != "measured":
        gives_way = in_bone == 1 and second.status == "measured"
        if first.why == _ANSWER_GATE_FAILED:
            gives_way = gives_way and _fits_clearly_better_and_as_witnessed(first, second)
        return (second if gives_way else first), None
    chosen, refusal = _settle_by_fit(first, second, views, sightings_prefer_second)
    if in_bone is None or out_of_bone_mm is None:
        return chosen, refusal
    placed = (first, second)[in_bone]
    if refusal is not None:
        return placed, None
    if chosen is placed or chosen.status != "measured":
        return chosen, None
    return chosen, (f"the two pins cannot be told apart in view {', '.join(views)}: the naming "
                    f"that fits puts a pin {out_of_bone_mm[1 - in_bone]:.0f} mm out of the "
                    "bone, the other has both pins in it; take a view from another angle")


# Where the fit and the pins' sightings disagree about the names, the encoders' motion
# settles it if it clearly sides with the fit: the views of the naming the fit chose
# strayed from it at most this share of the other's E_odo RMS. Of 204 naming decisions of
# fourteen realism scenes at level 1 (main ec69aae), 13 set fit against sightings: in the
# 11 where the fit was right its naming's share was 0.46-0.78, where it was wrong
# (scatter seed 17, 17 deg off) 0.87, and once (retractors seed 24, right) 1.06.
_ENCODERS_CONFIRM_SHARE = 0.6


def _encoders_confirm(chosen: _Solved, other: _Solved, share: float = _ENCODERS_CONFIRM_SHARE) -> bool:
    """Whether both were solved held to the encoders' motion and ``chosen``'s views stray
    from it at most ``share`` of ``other``'s (E_odo RMS): 1 for no more than the other."""
    if "E_odo" not in chosen.residual_rms or "E_odo" not in other.residual_rms:
        return False
    return chosen.residual_rms["E_odo"] <= share * other.residual_rms["E_odo"]


def _fits_clearly_better_and_as_witnessed(first: _Solved, second: _Solved) -> bool:
    """Whether ``second`` fits better than ``first`` by the naming margin, with views the
    encoders' motion contradicts no more (both solved held to it)."""
    return cost_gap(first, second) <= -NAMING_MIN_COST_GAP and _encoders_confirm(second, first, 1.0)


def _settle_by_fit(first: Solved, second: Solved, views: list[str],
                   sightings_prefer_second: bool | None = None) -> tuple[Solved, str | None]:
    """:func:`settle_naming` by the fit and the pins' sightings alone. A naming
    that fits clearly better wins only if the pins' sightings (at the first solve's poses,
    ``sightings_prefer_second``) do not favour the other, or the encoders' motion clearly
    does (:func:`_encoders_confirm`): on extracted contours the fit alone chose wrong names
    (two realism cases measured 17 and 25 deg off).

    A second naming that lost its way, or whose geometry is degenerate, leaves the first
    standing; one that fits about as well or better but failed an answer gate does not:
    the right naming may be the refused one (a simulated case was measured 4.1 deg off
    under the wrong names while the right ones left the pins 3.2 deg from parallel), and
    "about as well" is twice as wide where the sightings favour the refused one."""
    cost_first, cost_second = sum(first.term_costs.values()), sum(second.term_costs.values())
    gap = cost_gap(first, second)
    if second.status != "measured":
        # Where the pins' sightings favour the refused naming, the fit must say twice as
        # clearly that the first is right (processing seed 24: the other naming, refused by
        # 0.05 px at a bone gate, cost 107 more; the first was measured 12 deg off).
        needed = NAMING_MIN_COST_GAP * (2.0 if sightings_prefer_second else 1.0)
        if second.why == _ANSWER_GATE_FAILED and gap < needed:
            return first, (f"the two pins cannot be told apart in view {', '.join(views)}: the "
                           f"other naming fits as well (final cost {cost_second:.0f} against "
                           f"{cost_first:.0f}) but is refused ({second.reason}); take a view "
                           "from another angle")
        return first, None
    better = first if gap >= 0 else second
    if abs(gap) >= NAMING_MIN_COST_GAP:
        if sightings_prefer_second is None or sightings_prefer_second == (better is second):
            return better, None
        if _encoders_confirm(better, second if better is first else first):
            return better, None
        return better, (f"the two pins cannot be told apart in view {', '.join(views)}: the "
                        f"fit (final cost {cost_first:.0f} against {cost_second:.0f}) and "
                        "where the pins' sightings meet disagree about their names; take a "
                        "view from another angle")
    a, b = first.angles_deg, second.angles_deg
    assert a is not None and b is not None  # both measured
    apart = np.abs(np.subtract(a, b))
    if np.all(apart <= NAMING_PLANE_TOLERANCE_DEG):
        return better, None
    return better, (f"the two pins cannot be told apart in view {', '.join(views)}: both namings fit "
                    f"(final cost {cost_first:.0f} against {cost_second:.0f}) and give planes "
                    f"{apart[0]:.1f} deg apart in CTR and {apart[1]:.1f} deg in STR; take a view "
                    "from another angle")
