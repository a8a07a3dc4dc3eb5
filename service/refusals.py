"""Why a measurement was refused, as a stable code beside the sentence that explains it.

The pipeline and the solver explain a refusal in words for the surgeon; the SR's advice, the
result document (``refusal.code``), the metrics (a counter per code) and the re-run policy
read the :class:`RefusalCode` instead, so rewording a sentence changes none of them. The
solver names the kind of its refusals itself (``SolveOutcome.why``); :func:`solver_refusal`
carries it over.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from slamtka.solver.gates import Why

__all__ = ["CODES", "Code", "RefusalCode", "Refusal", "solver_refusal"]


class RefusalCode(StrEnum):
    """The pipeline's own codes; a solve's refusals carry the solver's (``Why``). The values
    of both are published (result.json, metrics labels): :data:`CODES`."""

    NO_PLAN = "no_plan"
    NO_CALIBRATION = "no_calibration"
    TOO_FEW_CONTOURS = "too_few_contours"
    OTHER = "other"


Code = RefusalCode | Why
CODES: tuple[str, ...] = tuple(c.value for c in RefusalCode) + tuple(w.value for w in Why)
_SOLVER_CODES = frozenset(w.value for w in Why)


# Codes a later re-run of the same views may clear, once the operator added what was missing
# (a plan, a calibration); the others need new views.
_MAY_RESTART = frozenset({RefusalCode.NO_PLAN, RefusalCode.NO_CALIBRATION})


@dataclass(frozen=True)
class Refusal:
    """One refused measurement: ``code`` for machines, ``detail`` for people, and whether a
    re-run without new views may succeed (``may_restart``)."""

    code: Code
    detail: str
    may_restart: bool

    @classmethod
    def of(cls, code: Code, detail: str) -> Refusal:
        return cls(code, detail, code in _MAY_RESTART)

    def to_json(self) -> dict:
        return {"code": self.code.value, "detail": self.detail, "may_restart": self.may_restart}

    @classmethod
    def from_json(cls, doc: dict) -> Refusal:
        """The refusal as a result document states it (its code one of :data:`CODES`)."""
        value = doc["code"]
        code: Code = Why(value) if value in _SOLVER_CODES else RefusalCode(value)
        return cls(code, doc["detail"], doc["may_restart"])


def solver_refusal(why: Why | None, reason: str) -> Refusal:
    """The refusal of a solve that returned ``not_measured``: the kind the solver named, and
    its sentence."""
    return Refusal.of(why or RefusalCode.OTHER, reason)
