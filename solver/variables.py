"""Names of the solver's pose variables and their column order (docs/solver.md).

Terms name the poses they touch by key, as GTSAM's factors name theirs by ``Symbol``:
:func:`view_key` (``T_cam_tibia`` of a view), :func:`pin_key` (``T_tibia_pin``) and :data:`BONE`,
whose frame is the tibia frame itself: the reference, not a variable. Where each pose's
six columns sit in the optimiser's system is decided by :class:`Ordering` alone, so no
term, stage or report counts views to find a pin.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

__all__ = ["BONE", "Ordering", "PoseKey", "body_key", "pin_key", "view_key"]

# The column order of the kinds of variables: views first, then pins.
_RANK = {"view": 0, "pin": 1}


class PoseKey(NamedTuple):
    """One rigid body's pose: ``kind`` "view" (``position``: its place among the problem's
    views), "pin" or "bone" (``label``: the observation label of its contours). A tuple, so
    that hashing and comparing keys (every term's pose look-ups, every iteration) cost no
    Python calls."""

    kind: str
    position: int = 0
    label: str = ""

    def __str__(self) -> str:
        return f"view{self.position}" if self.kind == "view" else self.label


def view_key(k: int) -> PoseKey:
    """The camera pose ``T_cam_tibia`` of the ``k``-th view."""
    return PoseKey("view", position=k)


def pin_key(label: str) -> PoseKey:
    """The pose ``T_tibia_pin`` of the pin ``label`` ("pin1", "pin2")."""
    return PoseKey("pin", label=label)


# The bone: its frame is the tibia frame, so its pose is the identity and never estimated.
BONE = PoseKey("bone", label="bone")


def body_key(label: str) -> PoseKey:
    """The body whose contours carry the observation ``label``."""
    return BONE if label == "bone" else pin_key(label)


@dataclass(frozen=True)
class Ordering:
    """The pose variables in their column order (views by index, then pins by label): the
    pose of ``keys[i]`` owns the six columns from ``6 i`` of the system, of every increment
    and covariance over all poses."""

    keys: tuple[PoseKey, ...]
    _index: dict[PoseKey, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index", {key: i for i, key in enumerate(self.keys)})

    @classmethod
    def of(cls, keys: Iterable[PoseKey]) -> Ordering:
        """The order of the variables ``keys``, whatever order they come in."""
        keys = tuple(keys)
        if any(key.kind not in _RANK for key in keys):
            raise ValueError("only view and pin poses are variables (the bone is the reference)")
        return cls(tuple(sorted(keys, key=lambda k: (_RANK[k.kind], k.position, k.label))))

    def __len__(self) -> int:
        return len(self.keys)

    def index(self, key: PoseKey) -> int:
        """The block (of six columns) of ``key``'s pose."""
        return self._index[key]

    def columns(self, keys: Iterable[PoseKey]) -> np.ndarray:
        """The columns of the poses ``keys``, in that order."""
        return np.concatenate([6 * self._index[key] + np.arange(6) for key in keys])

    def split(self, increments: np.ndarray) -> dict[PoseKey, np.ndarray]:
        """An increment of all poses (6P,) as each key's six."""
        return dict(zip(self.keys, increments.reshape(-1, 6)))

    def mask(self, dofs: Mapping[PoseKey, np.ndarray]) -> np.ndarray:
        """(6P,) booleans set where ``dofs`` (a key's six) are; False for keys not given."""
        out = np.zeros((len(self.keys), 6), bool)
        for key, row in dofs.items():
            out[self._index[key]] = row
        return out.reshape(-1)

    def marginal(self, covariance: np.ndarray, keys: Iterable[PoseKey]) -> np.ndarray:
        """The joint covariance of the poses ``keys`` out of one over all poses (6P, 6P)."""
        columns = self.columns(keys)
        return covariance[np.ix_(columns, columns)]
