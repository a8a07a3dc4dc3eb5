"""The calibration phantom as the product knows it: a plate carrying a grid of steel balls.

Only the nominal geometry lives here (the calibration fits the plate's real ball positions,
with the pitch as a scale); rendering images of it is the simulator's (slamtka.sim).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PhantomSpec"]


@dataclass(frozen=True)
class PhantomSpec:
    """Ball-grid plate: ``rows`` x ``cols`` balls ``pitch_mm`` apart (ball centres)."""

    rows: int = 5
    cols: int = 5
    pitch_mm: float = 25.0
    ball_diameter_mm: float = 3.0
    plate_thickness_mm: float = 6.0

    def __post_init__(self) -> None:
        if self.rows < 3 or self.cols < 3:
            raise ValueError(f"a {self.rows}x{self.cols} grid is too small to calibrate (>= 3x3)")
        if not 2.0 * self.ball_diameter_mm < self.pitch_mm <= 200.0:
            raise ValueError(f"pitch {self.pitch_mm} mm must exceed two ball diameters and be <= 200")
        if not 0.5 <= self.ball_diameter_mm <= 10.0:
            raise ValueError(f"ball diameter {self.ball_diameter_mm} mm is outside 0.5-10 mm")

    def points(self) -> np.ndarray:
        """Ball centres (rows*cols, 3) in the plate frame (mm), centred, z = 0."""
        j, i = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack([(j.ravel() - (self.cols - 1) / 2) * self.pitch_mm,
                                (i.ravel() - (self.rows - 1) / 2) * self.pitch_mm,
                                np.zeros(self.rows * self.cols)])

    def to_json(self) -> dict:
        return {"kind": "ball grid on acrylic plate", "rows": self.rows, "cols": self.cols,
                "pitch_mm": self.pitch_mm, "ball_diameter_mm": self.ball_diameter_mm}
