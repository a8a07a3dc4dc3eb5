"""Signed distance fields of models, sampled on a grid, with analytic gradients.

The back-projection term E_bp needs, thousands of times per iteration, the distance of a 3D
point to the tibia or pin surface and its gradient. Exact mesh queries are far too slow for
that, so the field is sampled once per plan on a regular grid (negative inside, millimetres,
in the model's own frame), cached on disk keyed by the meshes' hash, and queried by trilinear
interpolation whose gradient is the exact derivative of the interpolant (so Jacobians agree
with finite differences).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamtka.solver.kernels import trilinear
from slamtka.solver.plan_cache import cache_key, read_arrays, write_arrays
from slamtka.solver.surface import Surface, mesh_digest

__all__ = ["SignedDistanceField", "MAX_GRID_VOXELS"]

# Bump when the sampling scheme changes so stale caches are not reused.
_CACHE_VERSION = 1
# Exact distances are computed only within this many voxels of the surface; the far field is
# interpolated from a grid this many times coarser (its sign and slope are all that matter).
_BAND_VOXELS = 6
_COARSE_FACTOR = 4
# Largest grid built (4 bytes per voxel, sampled in slabs): the phantom's tibia with fibula at
# 1 mm needs 3.1 million voxels, the knee-smith2019 meshes 0.8 million and a large
# full-length leg about 6 million. 12 million leaves that margin while refusing meshes far
# apart or in the wrong units.
MAX_GRID_VOXELS = 12_000_000
# Grid points sampled at once while building: bounds the build's peak memory (libigl's
# outputs take about 300 bytes per point) to some 40 MB over the grid itself; the values
# do not depend on it.
_SLAB_POINTS = 131_072


def _exact_signed_distance(
    points: np.ndarray, meshes: Sequence[Surface], band_mm: float | None
) -> np.ndarray:
    """Signed distance (negative inside) to the union of ``meshes``; NaN beyond ``band_mm``."""
    import igl  # with scipy.sparse, ~25 MB: only building a field needs it, never a solve

    result = np.full(len(points), np.inf)
    bound = np.inf if band_mm is None else band_mm
    for mesh in meshes:
        # Pseudonormal signs are exact and fast on closed meshes; the winding number copes
        # with the holes of meshes that are not watertight.
        sign_type = (
            igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL
            if mesh.is_watertight
            else igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER
        )
        d = igl.signed_distance(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(mesh.vertices, dtype=np.float64),
            np.ascontiguousarray(mesh.faces, dtype=np.int64),
            sign_type=sign_type,
            lower_bound=-bound,
            upper_bound=bound,
        )[0]
        d = np.where(np.isfinite(d), d, np.nan)
        result = np.fmin(result, d)
    result[np.isinf(result)] = np.nan
    return result


@dataclass(frozen=True)
class SignedDistanceField:
    """A signed distance field on a regular grid: ``values[i, j, k]`` at ``origin + spacing*(i, j, k)``."""

    origin: np.ndarray
    spacing: float
    values: np.ndarray
    digest: str

    @staticmethod
    def build(
        meshes: Sequence[Surface], spacing_mm: float, margin_mm: float
    ) -> SignedDistanceField:
        """Sample the field of the union of ``meshes`` over their bounds plus ``margin_mm``.

        The grid is sampled a slab of x-planes at a time (``_SLAB_POINTS``): libigl's
        per-point outputs (closest points, normals) and the points themselves would
        otherwise take about 300 bytes per voxel at once (1.1 GB for the phantom)."""
        lo = np.min([m.bounds[0] for m in meshes], axis=0) - margin_mm
        hi = np.max([m.bounds[1] for m in meshes], axis=0) + margin_mm
        shape = np.ceil((hi - lo) / spacing_mm).astype(int) + 1
        voxels = int(np.prod(shape.astype(np.int64)))
        if voxels > MAX_GRID_VOXELS:
            extent = " x ".join(f"{e:.0f}" for e in hi - lo)
            raise ValueError(
                f"the models span {extent} mm: a distance field at {spacing_mm:g} mm would need "
                f"{voxels:,} voxels (at most {MAX_GRID_VOXELS:,}); check the mesh units and that "
                "the meshes lie together")
        coarse = SignedDistanceField._sample(meshes, lo, spacing_mm * _COARSE_FACTOR,
                                             shape // _COARSE_FACTOR + 2, band_mm=None)
        fine = SignedDistanceField._sample(meshes, lo, spacing_mm, shape,
                                           band_mm=_BAND_VOXELS * spacing_mm, far_field=coarse)
        return SignedDistanceField(lo, spacing_mm, fine.values, mesh_digest(meshes))

    @staticmethod
    def _sample(meshes: Sequence[Surface], origin: np.ndarray, spacing: float,
                shape: np.ndarray, band_mm: float | None,
                far_field: SignedDistanceField | None = None) -> SignedDistanceField:
        """Exact distances on the grid, slab by slab; beyond ``band_mm`` NaN, or the value
        interpolated from ``far_field`` when given (its sign and slope are all that matter)."""
        field = SignedDistanceField(origin, spacing, np.zeros(tuple(shape), np.float32), "")
        plane = int(shape[1]) * int(shape[2])
        step = max(1, _SLAB_POINTS // plane)
        for first in range(0, int(shape[0]), step):
            planes = slice(first, min(first + step, int(shape[0])))
            points = field.grid_points(planes)
            values = _exact_signed_distance(points, meshes, band_mm)
            far = np.isnan(values)
            if far_field is not None and far.any():
                values[far] = far_field.query(points[far], gradient=False)[0]
            field.values[planes] = values.reshape((-1,) + tuple(shape[1:]))
        return field

    @staticmethod
    def cached(
        meshes: Sequence[Surface], spacing_mm: float, margin_mm: float, cache_dir: Path | None
    ) -> SignedDistanceField:
        """Load the field from ``cache_dir`` if its key matches, else build and store it."""
        if cache_dir is None:
            return SignedDistanceField.build(meshes, spacing_mm, margin_mm)
        path = Path(cache_dir) / f"sdf-{cache_key(mesh_digest(meshes), spacing_mm, margin_mm, _CACHE_VERSION)}.npz"
        stored = read_arrays(path, "distance field")
        if stored is not None:
            return SignedDistanceField._of(stored)
        field = SignedDistanceField.build(meshes, spacing_mm, margin_mm)
        field.save(path)
        return field

    def bounds(self) -> np.ndarray:
        """(2, 3) lower and upper corners of the sampled box, model frame, mm."""
        return np.vstack([self.origin, self.origin + self.spacing * (np.array(self.values.shape) - 1)])

    def grid_points(self, planes: slice = slice(None)) -> np.ndarray:
        """Model-frame points (N, 3) of the grid's x-planes ``planes``, in ``values`` order."""
        axes = [self.origin[a] + self.spacing * np.arange(n) for a, n in enumerate(self.values.shape)]
        axes[0] = axes[0][planes]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def save(self, path: Path) -> None:
        write_arrays(path, origin=self.origin, spacing=self.spacing, values=self.values,
                     digest=np.array(self.digest))

    @staticmethod
    def load(path: Path) -> SignedDistanceField:
        with np.load(path) as data:
            return SignedDistanceField._of(data)

    @staticmethod
    def _of(arrays: Mapping[str, np.ndarray]) -> SignedDistanceField:
        return SignedDistanceField(arrays["origin"], float(arrays["spacing"]), arrays["values"],
                                   str(arrays["digest"]))

    def query(self, points: np.ndarray, gradient: bool = True
              ) -> tuple[np.ndarray, np.ndarray | None]:
        """Signed distances (N,) and gradients (N, 3) at model-frame points (N, 3); without
        ``gradient`` (ray searches, trial steps) only the distances, and None.

        Outside the grid the value grows with the distance to the grid (an upper bound of the
        true distance) and the gradient points back towards the grid, so far-away points are
        still pulled towards the model.
        """
        value, grad = trilinear(self.values, np.asarray(self.origin, float), float(self.spacing),
                                np.ascontiguousarray(points, dtype=float).reshape(-1, 3), gradient)
        return value, (grad if gradient else None)
