"""Quality gates: why a solve's inputs or answer cannot be trusted, said in words.

Each gate reads the figures the solver measured (:mod:`.diagnostics`) and the limits
(:class:`~slamtka.solver.solver_config.GateLimits`), and returns the reason (a sentence
naming the view, the model and the figure that failed) or None. The inputs are checked
before the solve (two views far enough apart, every model seen in two of them); the answer
after it (the contours fit the posed models, the pins' edge points agree about where each
pin is, the pins are the block's parallel pair, the views moved as the encoders measured).
A solve refused by an answer gate may have lost its way; the solver then restarts it from a
global search (:func:`solver.slam.solve_joint`).
"""

from __future__ import annotations

from enum import StrEnum

from slamtka.solver.diagnostics import InputDiagnostics, OutlineFit, SolveDiagnostics
from slamtka.solver.observations import PIN_LABELS
from slamtka.solver.pin_naming import PIN_OUT_OF_BONE_MM
from slamtka.solver.solver_config import GateLimits

__all__ = ["Why", "angle_uncertainty", "contour_misfit", "edge_on_plane_confirmed", "hidden_outline",
           "input_refusal", "odometry_misfit", "outline_misfit", "pin_divergence", "pin_out_of_bone",
           "pins_across_the_tibia", "pins_in_line", "pins_overlap", "shared_bar_unexplained",
           "sought_edges_missing", "view_separation"]


class Why(StrEnum):
    """Which kind of refusal a solve ends in: the stable code the service publishes beside
    the sentence (``service.refusals.RefusalCode`` holds every one of these values)."""

    TOO_FEW_VIEWS = "too_few_views"
    BONE_OUTLINE_INSUFFICIENT = "bone_outline_insufficient"
    PIN_NOT_SEEN = "pin_not_seen"
    PINS_INDISTINCT = "pins_indistinct"
    VIEWS_TOO_CLOSE = "views_too_close"
    GATE_FAILED = "gate_failed"  # the posed models do not fit what the images show
    ENCODERS_DISAGREE = "encoders_disagree"
    NOT_CONVERGED = "not_converged"
    DEGENERATE = "degenerate"


def input_refusal(d: InputDiagnostics, limits: GateLimits) -> tuple[Why, str] | None:
    """Why these inputs cannot give a trustworthy measurement (kind, sentence), or None."""
    n_views = len(d.view_ids)
    if n_views < 2:
        return Why.TOO_FEW_VIEWS, f"only {n_views} view(s); at least two are needed"
    bone_views = sum(d.point_counts[k, "bone"] >= limits.min_bone_points for k in range(n_views))
    if bone_views < 2:
        return Why.BONE_OUTLINE_INSUFFICIENT, (f"too few bone contour points: fewer than two views "
                                               f"have at least {limits.min_bone_points}")
    for label in PIN_LABELS:
        seen = sum(d.point_counts[k, label] >= limits.min_pin_points for k in range(n_views))
        if seen < 2:
            # Each view short of points named, with the extraction's note, else its count
            # (operating-room seed 15: a pin 49% hidden left 26 points, fewer once thinned).
            why = "".join(f"; view {view_id}: {label} " + (notes[label] if label in notes else
                                                            f"has {d.point_counts[k, label]} contour points")
                          for k, (view_id, notes) in enumerate(zip(d.view_ids, d.notes))
                          if d.point_counts[k, label] < limits.min_pin_points)
            return Why.PIN_NOT_SEEN, (f"{label} is not seen in two views (needs >= "
                                      f"{limits.min_pin_points} contour points in each; seen in "
                                      f"{seen}){why}")
    if d.view_separation_deg < limits.min_view_separation_deg:
        return Why.VIEWS_TOO_CLOSE, (f"views are too close in angle ({d.view_separation_deg:.1f} deg "
                                     f"apart; at least {limits.min_view_separation_deg:.0f} deg needed)")
    return None


def contour_misfit(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the contours do not fit the posed models, or None.

    Four checks: the re-projection RMS of the edge points (methods that have them), the share
    of each bone contour's pixels whose rays miss the bone (ditto), how far each pin's edge points
    lie from where their rays graze it (ditto), and, for every model in every view,
    the median distance between its silhouette traced at the final poses and the observed
    contour. A solve caught in a wrong basin can seat its edge points well (small
    re-projection RMS) while a model's outline lies off its contour, or fit each view's pin
    contours by a pin pose that none of them quite supports."""
    if d.reprojection_rms_px is not None and d.reprojection_rms_px > limits.max_residual_rms_px:
        return (f"contours do not fit the models (re-projection RMS "
                f"{d.reprojection_rms_px:.1f} px > {limits.max_residual_rms_px:.1f} px)")
    for stray in d.stray_shares:
        if stray.fraction > limits.max_stray_fraction:
            return (f"the {stray.label} contour of view {stray.view_id} does not fit its "
                    f"model ({100 * stray.fraction:.0f}% of its points lie more than "
                    f"{d.max_ray_miss_mm:g} mm off it > {100 * limits.max_stray_fraction:.0f}%)")
    for graze in d.pin_grazes:
        if graze.offset_mm > limits.max_pin_graze_offset_mm:
            return (f"the {graze.label} edge points of view {graze.view_id} "
                    f"lie off the pin ({graze.offset_mm:.2f} mm RMS from where their rays graze it "
                    f"> {limits.max_pin_graze_offset_mm} mm): "
                    f"the views disagree about where it is")
    return outline_misfit(d.outlines, limits.max_silhouette_median_px, limits)


def sought_edges_missing(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Where the bone contours were sought near the model's outline: the first view whose
    frame shows the bone's edge along too little of the outline at the solved poses, or None.
    Edges sought near a wrong pose fit it well (a femur's, a fibula's, noise at low dose
    lie near any outline), so the median fit proves little; a right pose finds its edge
    along most of its outline (65-92% on simulated frames; a rotation of 7 deg found 35%)."""
    for view_id, share in d.sought_edge_shares:
        if share < limits.min_sought_edge_share:
            return (f"the bone's edge, sought near its outline, is seen along only "
                    f"{100 * share:.0f}% of it in view {view_id} "
                    f"(< {100 * limits.min_sought_edge_share:.0f}%)")
    return None


def hidden_outline(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why too little of the bone's outline can be seen in some view to trust its fit, or
    None: where metal, collimator blades, text or the field's edge hide most of it, the
    fit of the rest cannot tell a wrong pose from a right one."""
    for fit in d.outlines:
        if fit.label == "bone" and fit.visible_share < limits.min_visible_outline_share:
            return (f"view {fit.view_id}: too little of the tibia outline is visible "
                    f"({100 * fit.visible_share:.0f}% of it < "
                    f"{100 * limits.min_visible_outline_share:.0f}%; metal, collimator blades "
                    f"or the field's edge hide the rest)")
    return None


def pins_overlap(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why some view cannot tell the two pins apart, or None: seen one behind the other,
    their shadows are one bar, and which of its edges is which pin's is a guess. Read when
    the contours do not fit, to name the cause (pins that cross in projection but fit are
    measured)."""
    for overlap in d.pin_overlaps:
        if overlap.share > limits.max_pin_overlap_share:
            return (f"view {overlap.view_id}: the two pins lie one behind the other "
                    f"({100 * overlap.share:.0f}% of a pin's shadow on the other's > "
                    f"{100 * limits.max_pin_overlap_share:.0f}%); take that view from another angle")
    return None


def pins_in_line(d: SolveDiagnostics) -> str | None:
    """Why no view shows how far apart the pins are, or None: where in every view both
    pins lie along one line and on each other, each pin's inner end hides in the other's
    shadow (an idealised case so was measured 4.2 deg off in CTR, its angle sigma 1.1 deg)."""
    if not d.pin_overlaps or not all(overlap.ends_hidden for overlap in d.pin_overlaps):
        return None
    return (f"views {', '.join(o.view_id for o in d.pin_overlaps)}: the two pins lie in line, one "
            "on the other, in every view, so no view shows how far apart they are; take a view "
            "from another angle")


def shared_bar_unexplained(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the fitted pins do not account for a view's one bar, or None: where the fit
    shared a bar's edges out between the pins, a pin may slide along its axis off its part
    of the bar, the views turning to make up for it (surgeon's views seed 26: pin 1 slid
    27 mm, 29% of the bar left off both pins, measured 0.95 deg off with a sigma of 0.15)."""
    for overlap in d.pin_overlaps:
        if overlap.unexplained_share > limits.max_unexplained_pin_edge_share:
            return (f"view {overlap.view_id}: {100 * overlap.unexplained_share:.0f}% of the pins' "
                    f"one bar lies off both fitted pins (> "
                    f"{100 * limits.max_unexplained_pin_edge_share:.0f}%), so which part is "
                    f"which pin's is not known; take that view from another angle")
    return None


def pin_divergence(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the solved pins cannot be the block's parallel pair, or None.

    Across the pins' plane the limit holds always: that tilt is the resection angles' own
    error. Within the plane the pins may turn further apart where the views cannot resolve
    that turn (within ``max_unresolved_turn_sds`` of its standard deviation): seen nearly
    edge-on in both views, the plane is sure but the pins' turn in it rests on their ends
    alone (seed 16 in eight scenes: 3.0-3.8 deg, the angles within 0.2 deg; at 2.6-3.5 sd
    it passes, at 4.2-5.7 sd it is still refused). A turn the views do resolve is a wrong
    pose however flat (surgeon's views seed 14: 4.4 deg within the plane, 10.6 sd, the
    plane 4.9 deg off), unless every view of a solve held to the encoders sees the plane
    edge-on (:func:`edge_on_plane_confirmed`). No turn past ``max_excused_turn_deg`` is
    excused: pins pointing across each other are a wrong pose, not an unresolved one."""
    divergence, limit_deg = d.pin_divergence, limits.max_pin_divergence_deg
    if divergence.out_of_plane > limit_deg:
        return (f"the pins are {divergence.total:.1f} deg from parallel ({divergence.out_of_plane:.1f} deg "
                f"across their plane > {limit_deg:g} deg): the cutting block holds them parallel, "
                f"so a pin's pose is wrong")
    unresolved = divergence.in_plane <= limits.max_excused_turn_deg and (
        edge_on_plane_confirmed(d, limits)
        or divergence.in_plane <= limits.max_unresolved_turn_sds * divergence.in_plane_sd)
    if divergence.total > limit_deg and not unresolved:
        return (f"the pins are {divergence.total:.1f} deg from parallel (> {limit_deg:g} deg): "
                f"the cutting block holds them parallel, so a pin's pose is wrong")
    return None


def edge_on_plane_confirmed(d: SolveDiagnostics, limits: GateLimits) -> bool:
    """Whether every view sees the pins' plane edge-on, from poses solved held to the
    encoders' motion: each view's line of pins seen from its source is then that plane,
    and nothing shows, nor changes the angles, how the pins turn within it (surgeon's views
    seeds 16 and 27: both views within 1.5 deg of edge-on, the pins 25-33 deg apart within
    their plane even solved from the truth, the angles within 0.45 deg). A view that sees
    the plane at a slant resolves that turn, so there it stays a sign of a wrong pose (the
    real tibia's views seed 27, one view 2.0 deg off edge-on: the pins 6.3 deg apart, STR
    0.88 deg off). Without the encoders, edge-on views may be the wrong poses that made
    them so (real tibia seed 2073 at level 2 solved without them: view 2 8 deg off, the
    pins 28 deg apart in a plane both views see within 0.9 deg of edge-on, CTR 1.45 deg
    off); with them, a solve whose views the encoders contradict is refused by its own gate
    (:func:`odometry_misfit`)."""
    return d.pins_plane_elevation_deg <= limits.max_edge_on_elevation_deg and "E_odo" in d.residual_rms


def odometry_misfit(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the solved views disagree with the encoders' measured C-arm motion, or None.

    The contours of a wrong basin can be fitted by views the C-arm never moved between:
    the pins' and bone's edges then look fine while the relative pose of the views strays
    many sigmas from what the encoders measured (none when the solve had no E_odo)."""
    odo = d.residual_rms.get("E_odo")
    limit_sigma = limits.max_odometry_rms_sigma
    if odo is None or odo <= limit_sigma:
        return None
    return (f"the views disagree with the encoders' C-arm motion (E_odo residual "
            f"{odo:.1f} sigma RMS > {limit_sigma:g}): a local minimum")


def pin_out_of_bone(out_of_bone_mm: float | None) -> str | None:
    """Why the solved pins cannot be the ones drilled into the tibia, or None: the deeper
    end of one lies clearly outside the bone (``out_of_bone_mm``, None where the views
    cannot say how deep the pins are)."""
    if out_of_bone_mm is None or out_of_bone_mm < PIN_OUT_OF_BONE_MM:
        return None
    return (f"a solved pin does not reach into the tibia (its deeper end {out_of_bone_mm:.0f} mm "
            f"outside the bone >= {PIN_OUT_OF_BONE_MM:g} mm): the pins are drilled into it, so a "
            "pin's pose is wrong")


def pins_across_the_tibia(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the solved pins cannot be the block's, or None: their mean axis runs further
    from the tibia's front-to-back axis than ``max_pin_from_anteroposterior_deg``.

    The cutting block sits on the front of the tibia and its pins are drilled through it
    towards the back: within some 20 deg of that axis (the block turned about the tibia's
    axis, the cut tilted). Two parallel pieces of retractor blades seen in both views can
    triangulate to a parallel pair that fits every other gate (the real tibia, retractors
    and surgeon's views seed 14: both "pins" 73-75 deg from that axis, running nearly from
    side to side, measured 4.9 deg off in STR). The pins' mean axis is read, not each
    pin's: a right solve of pins seen edge-on in every view may leave one pin 37 deg from
    that axis and the other 5 (surgeon's views seed 16)."""
    off_deg, limit_deg = d.pins_from_anteroposterior_deg, limits.max_pin_from_anteroposterior_deg
    if off_deg <= limit_deg:
        return None
    return (f"the solved pins run {off_deg:.0f} deg from the tibia's front-to-back axis (> {limit_deg:g} deg): "
            "the pins are drilled through the cutting block from the front, so other steel was taken "
            "for them")


def view_separation(d: SolveDiagnostics, limits: GateLimits) -> str | None:
    """Why the solved views are too close in angle to measure from, or None."""
    if d.view_separation_deg < limits.min_view_separation_deg:
        return f"views are too close in angle ({d.view_separation_deg:.1f} deg apart)"
    return None


def angle_uncertainty(max_sigma_deg: float, limits: GateLimits) -> str | None:
    """Why the measured angles are too uncertain to report (degenerate geometry), or None."""
    if max_sigma_deg > limits.max_angle_sigma_deg:
        return (f"geometry is degenerate: angle uncertainty {max_sigma_deg:.2f} deg "
                f"exceeds {limits.max_angle_sigma_deg:.1f} deg")
    return None


def outline_misfit(outlines: tuple[OutlineFit, ...], limit_px: float, limits: GateLimits
                   ) -> str | None:
    """The first model whose silhouette lies further than ``limit_px`` (median, both sides)
    from its observed contour in some view, or, for a pin, a tenth of whose outline lies
    further than ``max_pin_outline_p90_px``, said in words."""
    pin_limit_px = limits.max_pin_outline_p90_px
    for fit in outlines:
        where = f"the {fit.label} outline in view {fit.view_id}"
        if fit.median_px > limit_px:
            return (f"{where} does not lie on its contour (median distance {fit.median_px:.1f} px "
                    f"> {limit_px:.1f} px)")
        if fit.p90_px is not None and fit.p90_px > pin_limit_px:
            return (f"{where} leaves its contour (a tenth of it lies {fit.p90_px:.0f} px or more "
                    f"away > {pin_limit_px:.1f} px)")
    return None
