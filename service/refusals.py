"""Why a measurement was refused, as a stable code beside the sentence that explains it.

The pipeline and the solver explain a refusal in words for the surgeon; the SR's advice, the
result document (``refusal.code``), the metrics (a counter per code) and the re-run policy
read the :class:`RefusalCode` instead, so rewording a sentence changes none of them. The
solver (a separate package) still says why in words: :func:`solver_refusal` names its code.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

__all__ = ["RefusalCode", "Refusal", "solver_refusal"]


class RefusalCode(StrEnum):
    """The stable codes; the values are published (result.json, metrics labels)."""

    NO_PLAN = "no_plan"
    NO_CALIBRATION = "no_calibration"
    TOO_FEW_VIEWS = "too_few_views"
    TOO_FEW_CONTOURS = "too_few_contours"
    BONE_OUTLINE_INSUFFICIENT = "bone_outline_insufficient"
    PIN_NOT_SEEN = "pin_not_seen"
    PINS_INDISTINCT = "pins_indistinct"  # which pin is which cannot be told across the views
    VIEWS_TOO_CLOSE = "views_too_close"
    GATE_FAILED = "gate_failed"
    ENCODERS_DISAGREE = "encoders_disagree"
    NOT_CONVERGED = "not_converged"
    DEGENERATE = "degenerate"
    OTHER = "other"


# Codes a later re-run of the same views may clear, once the operator added what was missing
# (a plan, a calibration); the others need new views.
_MAY_RESTART = frozenset({RefusalCode.NO_PLAN, RefusalCode.NO_CALIBRATION})


@dataclass(frozen=True)
class Refusal:
    """One refused measurement: ``code`` for machines, ``detail`` for people, and whether a
    re-run without new views may succeed (``may_restart``)."""

    code: RefusalCode
    detail: str
    may_restart: bool

    @classmethod
    def of(cls, code: RefusalCode, detail: str) -> Refusal:
        return cls(code, detail, code in _MAY_RESTART)

    def to_json(self) -> dict:
        return {"code": self.code.value, "detail": self.detail, "may_restart": self.may_restart}


# The solver's gates (solver/gates.py, solver/slam.py, solver/pin_naming.py) by a phrase of their sentence, first
# match wins; the order puts the specific gates before the general ones.
_SOLVER_PHRASES = (
    ("view(s); at least two", RefusalCode.TOO_FEW_VIEWS),
    ("too few bone contour points", RefusalCode.BONE_OUTLINE_INSUFFICIENT),
    ("is not seen in two views", RefusalCode.PIN_NOT_SEEN),
    ("cannot be told apart", RefusalCode.PINS_INDISTINCT),
    ("too close in angle", RefusalCode.VIEWS_TOO_CLOSE),
    ("did not converge", RefusalCode.NOT_CONVERGED),
    ("geometry is degenerate", RefusalCode.DEGENERATE),
    ("does not fit", RefusalCode.GATE_FAILED),
    ("do not fit", RefusalCode.GATE_FAILED),
    ("lie off the pin", RefusalCode.GATE_FAILED),
    ("from parallel", RefusalCode.GATE_FAILED),
    ("disagree with the encoders", RefusalCode.ENCODERS_DISAGREE),
    ("does not lie on its contour", RefusalCode.GATE_FAILED),
    ("leaves its contour", RefusalCode.GATE_FAILED),
)


def solver_refusal(reason: str) -> Refusal:
    """The refusal of a solve that returned ``not_measured`` with ``reason``."""
    code = next((c for phrase, c in _SOLVER_PHRASES if phrase in reason), RefusalCode.OTHER)
    return Refusal.of(code, reason)
