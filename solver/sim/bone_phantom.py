"""Built-in parametric tibia + fibula phantom (left or right leg).

The phantom is the default patient model for simulations and the demo. Its
silhouette has to look like real bone from every direction around the leg
(kidney-shaped plateau, eminence, tuberosity, triangular twisted shaft,
malleoli, a separate fibula), otherwise 2D-3D registration on it would be
better or worse posed than on a real patient.

Construction: each bone is a loft of closed horizontal contours with the same
number of vertices per ring, closed by two caps shaped as height fields, i.e. a
topological sphere that is watertight by construction. Tibia contours are the
zero set of a 2D signed-distance-like function of height (plateau -> metaphysis
-> triangular shaft -> distal metaphysis), found by ray casting from a centre
line; the fibula contours are analytic ellipses. The fibula is carved out of the
tibia (fibular notch, fibular facet) so the two bones touch without overlapping.

Anatomical frame (all outputs, millimetres): origin at the knee centre (centre
of the plateau at the level of the articular surfaces), +z = mechanical axis
pointing proximally (the ankle centre lies on -z), +y anterior, +x = y cross z
(the patient's right). The geometry is designed for a right leg (medial = -x,
fibula at +x) and mirrored in x for a left leg.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
import trimesh
from scipy.interpolate import PchipInterpolator

from slamtka.solver.anatomy import Landmarks
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.plan import Plan, Target
from slamtka.solver.surface import Surface

__all__ = ["PhantomBone", "build_phantom", "phantom_plan", "MIN_LENGTH_MM", "MAX_LENGTH_MM"]

Array = np.ndarray

# ---------------------------------------------------------------------------
# Accepted overall tibia length (plateau articular level to the tip of the
# medial malleolus), mm: the adult range the dimensions below are scaled for.
MIN_LENGTH_MM = 350.0
MAX_LENGTH_MM = 400.0

# Mesh resolution. Faces ~ 2 * vertices-per-ring * rings; keeps the tibia in
# 10k-40k faces and the fibula in 3k-15k faces (silhouettes, distance fields).
TIBIA_RING_VERTICES = 120
FIBULA_RING_VERTICES = 48
TOP_CAP_RINGS = 24          # concentric rings of the plateau height field
BOTTOM_CAP_RINGS = 16       # concentric rings of the distal (plafond) height field
EDGE_ROUND_RINGS = 4        # rings rounding the rim between cap and wall
RIM_TRANSITION_RINGS = 3    # vertical rings from a non-planar cap rim to the walls
FIBULA_DOME_RINGS = 8       # rings of each fibular end dome

# ---------------------------------------------------------------------------
# Tibial plateau outline (right leg, x lateral, y anterior), mm. Union of the
# medial condyle (larger, oval), the lateral condyle (smaller, rounder) and an
# anterior fill, minus the posterior intercondylar notch: ~75 ML x ~48 AP,
# kidney-shaped seen from above.
MEDIAL_CONDYLE_CENTRE = (-16.5, -1.0)
MEDIAL_CONDYLE_SEMI_AXES = (21.0, 24.0)
LATERAL_CONDYLE_CENTRE = (17.5, -2.0)
LATERAL_CONDYLE_SEMI_AXES = (19.5, 21.0)
ANTERIOR_PLATEAU_CENTRE = (0.0, 5.0)
ANTERIOR_PLATEAU_SEMI_AXES = (25.0, 18.0)
POSTERIOR_NOTCH_CENTRE = (1.0, -31.0)
POSTERIOR_NOTCH_RADIUS = 11.0
PLATEAU_BLEND_MM = 5.0      # fillet radius between the plateau parts

# Plateau articular surface (height field above the outline), mm / degrees.
POSTERIOR_SLOPE_DEG = 7.0   # plateau descends posteriorly (tibial slope)
MEDIAL_DISH_CENTRE = (-18.0, -1.0)
MEDIAL_DISH_SEMI_AXES = (15.0, 18.0)
MEDIAL_DISH_DEPTH_MM = 2.5  # the medial plateau is clearly concave
LATERAL_DISH_CENTRE = (18.0, -2.0)
LATERAL_DISH_SEMI_AXES = (13.0, 14.0)
LATERAL_DISH_DEPTH_MM = 1.2  # the lateral plateau is nearly flat
MEDIAL_SPINE_CENTRE = (-4.5, 0.0)   # medial intercondylar tubercle
LATERAL_SPINE_CENTRE = (5.0, -2.0)  # lateral intercondylar tubercle
MEDIAL_SPINE_HEIGHT_MM = 9.0
LATERAL_SPINE_HEIGHT_MM = 8.0
SPINE_SIGMA_MM = (3.3, 5.0)         # ML, AP spread of a tubercle
EMINENCE_RIDGE_HEIGHT_MM = 3.0      # low ridge joining the tubercles
EMINENCE_RIDGE_SIGMA_MM = (7.0, 9.0)
PLATEAU_EDGE_RADIUS_MM = 2.5        # rounding of the plateau rim
# Pole of the plateau cap mesh: in the flat anterior intercondylar area, so the
# fan of thin triangles around it stays flat (no folds on the eminence).
TOP_CAP_POLE = (0.0, 12.0)

# Proximal metaphysis, mm below the plateau.
PLATEAU_RIM_DEPTH_MM = 8.0   # near-vertical condylar rim below the surface
METAPHYSIS_END_MM = 80.0     # where the flare has narrowed into the shaft
TUBEROSITY_CENTRE = (4.0, 18.5, -35.0)      # x, y, z; midline-to-lateral
TUBEROSITY_SEMI_AXES = (12.0, 8.0, 22.0)
TUBEROSITY_BLEND_MM = 6.0

# Diaphysis: a rounded triangle (anterior crest, posteromedial border,
# interosseous border facing the fibula), counter-clockwise, in the shaft's
# local frame, mm. Scaled along the shaft (narrowest in the distal third).
SHAFT_TRIANGLE = ((1.0, 22.0), (-15.0, -9.0), (14.5, -6.0))
SHAFT_CORNER_SOFTNESS_MM = 1.6
SHAFT_ELLIPSE_SEMI_AXES = (13.0, 14.0)   # rounds the flat faces slightly
SHAFT_CENTRE_Y_MM = 2.0      # shaft sits a little anterior to plateau centre
SHAFT_ANTERIOR_BOW_MM = 3.0  # mild anterior convexity of the diaphysis
# (depth / length, size factor of the triangle): narrowest in the distal third.
SHAFT_SCALE_PROFILE = ((0.2, 1.25), (0.45, 1.0), (0.68, 0.88), (1.0, 0.92))
# (depth / length, share of the ellipse): the distal shaft is rounder.
SHAFT_ROUNDNESS_PROFILE = ((0.2, 0.15), (0.5, 0.2), (0.75, 0.45), (1.0, 0.5))

# Distal metaphysis: rounded quadrilateral (anterolateral, anteromedial,
# posteromedial, posterolateral), counter-clockwise, distal local frame, mm:
# ~47 ML x ~32 AP above the plafond.
DISTAL_QUAD = ((22.0, 12.0), (-25.5, 14.0), (-24.5, -16.0), (22.0, -14.5))
DISTAL_CORNER_SOFTNESS_MM = 3.0
DISTAL_FLARE_START_MM = 100.0  # above the malleolar tip: concave flare begins
DISTAL_WALL_MM = 17.0          # above the malleolar tip: full width, vertical below
TIBIAL_TORSION_DEG = 18.0      # external torsion of the distal end

# Distal articular end (distal local frame, heights above the malleolar tip).
PLAFOND_HEIGHT_MM = 13.0            # plafond level above the medial malleolus tip
PLAFOND_VAULT_MM = 2.0              # plafond is concave (vaulted up)
PLAFOND_VAULT_SEMI_AXES = (20.0, 15.0)
MEDIAL_MALLEOLUS_TIP = (-17.5, 2.0)  # x, y of the tip (distal frame)
MEDIAL_MALLEOLUS_SEMI_AXES = (10.0, 13.0)  # footprint at plafond level
MEDIAL_MALLEOLUS_LANDMARK_MM = 9.0  # landmark height above its tip
MEDIAL_MALLEOLUS_BLUNTNESS = 1.3   # >1: blunt tip, steep articular face
DISTAL_EDGE_RADIUS_MM = 2.0
DISTAL_BLEND_MM = 3.0

# Fibula (right leg), mm. Centre line control points: proximal ones in the
# anatomical frame (z below plateau), distal ones in the distal tibial frame
# (z above the medial malleolus tip) so the fibula always sits in the notch.
FIBULA_PROXIMAL_CENTRE_LINE = (  # (depth below plateau, x, y)
    (19.0, 32.0, -20.0),
    (25.0, 32.0, -19.5),
    (48.0, 30.5, -15.5),
    (100.0, 29.5, -12.0),
)
FIBULA_MID_BOW_MM = (1.5, -2.5)     # lateral/posterior bow at mid-shaft
FIBULA_DISTAL_CENTRE_LINE = (  # (height above medial malleolus tip, x, y)
    (80.0, 27.0, -3.0),
    (35.0, 27.0, -3.5),
    (12.0, 28.5, -4.0),
    (0.0, 29.5, -4.0),
    (-6.0, 30.0, -4.0),
)
FIBULA_HEAD_TOP_MM = 13.0          # apex of the head below the plateau
FIBULA_HEAD_DOME_MM = 6.0          # height of the rounded head apex
LATERAL_MALLEOLUS_DROP_MM = 12.0   # tip below the medial malleolus tip
LATERAL_MALLEOLUS_DOME_MM = 6.0
LATERAL_MALLEOLUS_LANDMARK_MM = 12.0  # landmark height above its tip
# Section along the fibula: semi-axes (ML, AP) and triangularity of the shaft;
# head ~25 mm across, shaft ~13 mm, lateral malleolus ~14 x 22 mm.
FIBULA_PROXIMAL_PROFILE = (  # (depth below plateau, ML, AP, triangularity)
    (19.0, 12.5, 12.0, 0.0),
    (27.0, 12.5, 12.5, 0.0),
    (37.0, 9.5, 9.5, 0.02),
    (51.0, 7.0, 7.0, 0.06),
    (95.0, 6.5, 6.5, 0.08),
)
FIBULA_DISTAL_PROFILE = (  # (height above medial malleolus tip, ML, AP, tri.)
    (90.0, 6.0, 6.5, 0.08),
    (45.0, 6.5, 8.0, 0.05),
    (20.0, 7.0, 10.0, 0.02),
    (5.0, 7.0, 11.0, 0.0),
    (-6.0, 6.5, 10.0, 0.0),
)
FIBULA_NOTCH_GAP_MM = 1.0          # clearance carved between fibula and tibia
FIBULA_CARVE_BLEND_MM = 3.0
FIBULA_CLEARANCE_WINDOW_MM = 2.0  # > tibia ring spacing near the joints
FIBULA_EXACT_DISTANCE_MM = 5.0    # > gap + blend: farther, a bound suffices


@dataclass(frozen=True)
class PhantomBone:
    """Phantom tibia and fibula in the anatomical frame (mm, see module doc)."""

    tibia: trimesh.Trimesh      # watertight, outward normals, millimetres
    fibula: trimesh.Trimesh     # watertight, separate mesh, touches the tibia only
    knee_centre: np.ndarray     # (3,) mm, centre of the tibial plateau (origin)
    ankle_centre: np.ndarray    # (3,) mm, midpoint between the malleoli, on -z
    anterior: np.ndarray        # (3,) unit vector, anterior direction (+y)
    side: str                   # "left" or "right"


def build_phantom(side: str = "right", length_mm: float = 370.0) -> PhantomBone:
    """Build the phantom for one leg.

    length_mm is the tibia length from the plateau articular level to the tip
    of the medial malleolus (350..400 mm); the ankle centre ends up a few mm
    above that tip, at (0, 0, -L). Deterministic, takes well under a second.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    length = float(length_mm)
    if not MIN_LENGTH_MM <= length <= MAX_LENGTH_MM:
        raise ValueError(
            f"length_mm must be within [{MIN_LENGTH_MM:g}, {MAX_LENGTH_MM:g}] mm "
            f"(adult tibia), got {length_mm!r}"
        )
    design = _RightLegDesign(length)
    tibia = _build_tibia(design)
    fibula = _build_fibula(design)
    ankle = np.array([0.0, 0.0, design.ankle_z])
    if side == "left":
        tibia, fibula = _mirror_x(tibia), _mirror_x(fibula)
    return PhantomBone(
        tibia=tibia,
        fibula=fibula,
        knee_centre=np.zeros(3),
        ankle_centre=ankle,
        anterior=np.array([0.0, 1.0, 0.0]),
        side=side,
    )


# ---------------------------------------------------------------------------
# Small geometric helpers (vectorised, broadcast over any shape).


def _smoothstep(edge0: float, edge1: float, x: Array) -> Array:
    """C1 ramp from 0 at edge0 to 1 at edge1 (edges may be decreasing)."""
    t = np.clip((np.asarray(x, dtype=float) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _smin(a: Array, b: Array, k: float) -> Array:
    """Smooth minimum (union of distance fields with a fillet of size k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1.0 - h) + a * h - k * h * (1.0 - h)


def _smax(a: Array, b: Array, k: float) -> Array:
    """Smooth maximum (intersection / subtraction of distance fields)."""
    return -_smin(-a, -b, k)


def _ellipse_sdf(x: Array, y: Array, centre: tuple[float, float],
                 semi_axes: tuple[float, float]) -> Array:
    """Approximate signed distance to an axis-aligned ellipse (exact zero set)."""
    dx = (x - centre[0]) / semi_axes[0]
    dy = (y - centre[1]) / semi_axes[1]
    k0 = np.hypot(dx, dy)
    k1 = np.hypot(dx / semi_axes[0], dy / semi_axes[1])
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _ellipsoid_sdf(p: tuple[Array, Array, Array], centre: tuple[float, float, float],
                   semi_axes: tuple[float, float, float]) -> Array:
    """Approximate signed distance to an axis-aligned ellipsoid."""
    q = [(pi - ci) / ri for pi, ci, ri in zip(p, centre, semi_axes)]
    k0 = np.sqrt(sum(qi * qi for qi in q))
    k1 = np.sqrt(sum((qi / ri) ** 2 for qi, ri in zip(q, semi_axes)))
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _soft_polygon_sdf(x: Array, y: Array, vertices: tuple[tuple[float, float], ...],
                      softness: float) -> Array:
    """Convex polygon (counter-clockwise) with rounded corners.

    Log-sum-exp of the edge half-plane distances: a smooth, convex shape that
    stays inside the sharp polygon, corners rounded over ~softness mm.
    """
    x, y = np.broadcast_arrays(x, y)
    v = np.asarray(vertices, dtype=float)
    edges = np.roll(v, -1, axis=0) - v
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = np.einsum("ij,ij->i", normals, v)
    d = (normals[:, 0, None] * x.reshape(-1) + normals[:, 1, None] * y.reshape(-1)
         - offsets[:, None]) / softness
    m = d.max(axis=0)
    return (softness * (m + np.log(np.exp(d - m).sum(axis=0)))).reshape(x.shape)


def _bump(x: Array, y: Array, centre: tuple[float, float],
          semi_axes: tuple[float, float]) -> Array:
    """Smooth compact bump: 1 at the centre, 0 outside the ellipse."""
    q = ((x - centre[0]) / semi_axes[0]) ** 2 + ((y - centre[1]) / semi_axes[1]) ** 2
    return np.clip(1.0 - q, 0.0, None) ** 2


def _gauss(x: Array, y: Array, centre: tuple[float, float],
           sigma: tuple[float, float]) -> Array:
    """Anisotropic Gaussian of unit height."""
    return np.exp(-0.5 * (((x - centre[0]) / sigma[0]) ** 2
                          + ((y - centre[1]) / sigma[1]) ** 2))


def _rotate(x: Array, y: Array, angle: Array) -> tuple[Array, Array]:
    """Rotate points counter-clockwise (seen from +z) by angle (rad)."""
    c, s = np.cos(angle), np.sin(angle)
    return c * x - s * y, s * x + c * y


def _ring_heights(z_top: float, z_bottom: float,
                  spacing: Callable[[Array], Array]) -> Array:
    """Ring heights from z_top down to z_bottom with a local spacing (mm)."""
    fine = np.linspace(z_top, z_bottom, 4000)
    step = np.abs(np.diff(fine))
    density = 1.0 / spacing(0.5 * (fine[1:] + fine[:-1]))
    cumulative = np.concatenate([[0.0], np.cumsum(step * density)])
    count = max(int(round(cumulative[-1])), 1)
    return np.interp(np.linspace(0.0, cumulative[-1], count + 1), cumulative, fine)


# ---------------------------------------------------------------------------
# Right-leg design: all z-dependent anatomy of tibia and fibula.


class _RightLegDesign:
    """Tibia and fibula geometry of a right leg of a given length (mm)."""

    def __init__(self, length: float) -> None:
        self.length = length
        L = length
        self.z_tip = -L                                   # medial malleolus tip
        self.z_top_wall = -PLATEAU_RIM_DEPTH_MM           # plateau shape above
        self.z_bottom_wall = -L + DISTAL_WALL_MM          # distal shape below
        self.torsion = -np.radians(TIBIAL_TORSION_DEG)    # external = clockwise

        # Distal local frame: rotated by the torsion, centred so that the
        # midpoint of the malleolar landmarks lies on the mechanical axis.
        medial_landmark = np.array(MEDIAL_MALLEOLUS_TIP)
        lateral_landmark = np.array(self._fibula_distal_xy_local(
            np.array(LATERAL_MALLEOLUS_LANDMARK_MM - LATERAL_MALLEOLUS_DROP_MM)))
        mid = 0.5 * (medial_landmark + lateral_landmark)
        mx, my = _rotate(mid[0], mid[1], self.torsion)
        self.distal_centre = -np.array([mx, my])
        self.ankle_z = 0.5 * ((self.z_tip + MEDIAL_MALLEOLUS_LANDMARK_MM)
                              + (self.z_tip - LATERAL_MALLEOLUS_DROP_MM
                                 + LATERAL_MALLEOLUS_LANDMARK_MM))

        self._build_fibula_curves()

    # --- tibia: frames along the shaft ------------------------------------

    def twist(self, z: Array) -> Array:
        """Torsion angle (rad) of the shaft section at height z."""
        return self.torsion * _smoothstep(-METAPHYSIS_END_MM, self.z_bottom_wall, z)

    def shaft_centre(self, z: Array) -> tuple[Array, Array]:
        """Centre of the shaft/distal section: towards the distal centre, bowed."""
        t = _smoothstep(-0.5 * METAPHYSIS_END_MM, self.z_bottom_wall, z)
        bow = SHAFT_ANTERIOR_BOW_MM * np.sin(np.pi * t)
        return (t * self.distal_centre[0],
                (1.0 - t) * SHAFT_CENTRE_Y_MM + t * self.distal_centre[1] + bow)

    def metaphysis_weight(self, z: Array) -> Array:
        """0 on the plateau rim, 1 where the shaft begins (condyles, then a concave flare)."""
        return _smoothstep(self.z_top_wall, -METAPHYSIS_END_MM, z)

    def ray_centre(self, z: Array) -> tuple[Array, Array]:
        """Point inside every tibia section from which contours are ray cast."""
        w = self.metaphysis_weight(z)
        sx, sy = self.shaft_centre(z)
        return w * sx, w * sy

    def to_distal_local(self, x: Array, y: Array) -> tuple[Array, Array]:
        """Anatomical xy -> distal tibial frame (undo centre and torsion)."""
        return _rotate(x - self.distal_centre[0], y - self.distal_centre[1],
                       -self.torsion)

    # --- tibia: section distance function ---------------------------------

    def _plateau_sdf(self, x: Array, y: Array) -> Array:
        medial = _ellipse_sdf(x, y, MEDIAL_CONDYLE_CENTRE, MEDIAL_CONDYLE_SEMI_AXES)
        lateral = _ellipse_sdf(x, y, LATERAL_CONDYLE_CENTRE, LATERAL_CONDYLE_SEMI_AXES)
        anterior = _ellipse_sdf(x, y, ANTERIOR_PLATEAU_CENTRE, ANTERIOR_PLATEAU_SEMI_AXES)
        body = _smin(_smin(medial, lateral, PLATEAU_BLEND_MM), anterior, PLATEAU_BLEND_MM)
        notch = np.hypot(x - POSTERIOR_NOTCH_CENTRE[0],
                         y - POSTERIOR_NOTCH_CENTRE[1]) - POSTERIOR_NOTCH_RADIUS
        return _smax(body, -notch, PLATEAU_BLEND_MM)

    def _shaft_sdf(self, u: Array, v: Array, z: Array) -> Array:
        """Rounded triangular diaphysis, scaled along z (local coordinates)."""
        depth = -z / self.length
        scale = np.interp(depth, *zip(*SHAFT_SCALE_PROFILE))
        roundness = np.interp(depth, *zip(*SHAFT_ROUNDNESS_PROFILE))
        us, vs = u / scale, v / scale
        tri = _soft_polygon_sdf(us, vs, SHAFT_TRIANGLE, SHAFT_CORNER_SOFTNESS_MM)
        ell = _ellipse_sdf(us, vs, (0.0, 0.0), SHAFT_ELLIPSE_SEMI_AXES)
        return scale * ((1.0 - roundness) * tri + roundness * ell)

    def _distal_sdf(self, u: Array, v: Array) -> Array:
        return _soft_polygon_sdf(u, v, DISTAL_QUAD, DISTAL_CORNER_SOFTNESS_MM)

    def tibia_sdf(self, x: Array, y: Array, z: Array, carve: bool = True) -> Array:
        """Signed distance-like field of the tibia section at height z (<0 inside).

        Heights above the plateau rim / below the distal wall are clamped so the
        walls there are vertical and meet the height-field caps exactly. carve
        removes the fibula (plus a gap); it can be skipped where the fibula is
        far from the tibia (mid-shaft), which saves most of the build time.
        """
        z = np.clip(z, self.z_bottom_wall, self.z_top_wall)
        sx, sy = self.shaft_centre(z)
        u, v = _rotate(x - sx, y - sy, -self.twist(z))
        w_flare = np.clip((z - self.z_tip - DISTAL_FLARE_START_MM)
                          / (DISTAL_WALL_MM - DISTAL_FLARE_START_MM), 0.0, 1.0) ** 2
        lower = (1.0 - w_flare) * self._shaft_sdf(u, v, z) + w_flare * self._distal_sdf(u, v)
        w = self.metaphysis_weight(z)
        f = (1.0 - w) * self._plateau_sdf(x, y) + w * lower
        tuberosity = _ellipsoid_sdf((x, y, z), TUBEROSITY_CENTRE, TUBEROSITY_SEMI_AXES)
        f = _smin(f, tuberosity, TUBEROSITY_BLEND_MM)
        if not carve:
            return f
        keep_out = self.fibula_clearance_sdf(x, y, z) - FIBULA_NOTCH_GAP_MM
        return _smax(f, -keep_out, FIBULA_CARVE_BLEND_MM)

    # --- tibia: cap height fields -----------------------------------------

    def plateau_height(self, x: Array, y: Array) -> Array:
        """Articular surface of the plateau: slope, condylar dishes, eminence."""
        h = np.tan(np.radians(POSTERIOR_SLOPE_DEG)) * y
        h -= MEDIAL_DISH_DEPTH_MM * _bump(x, y, MEDIAL_DISH_CENTRE, MEDIAL_DISH_SEMI_AXES)
        h -= LATERAL_DISH_DEPTH_MM * _bump(x, y, LATERAL_DISH_CENTRE, LATERAL_DISH_SEMI_AXES)
        medial = MEDIAL_SPINE_HEIGHT_MM * _gauss(x, y, MEDIAL_SPINE_CENTRE, SPINE_SIGMA_MM)
        lateral = LATERAL_SPINE_HEIGHT_MM * _gauss(x, y, LATERAL_SPINE_CENTRE, SPINE_SIGMA_MM)
        ridge = EMINENCE_RIDGE_HEIGHT_MM * _gauss(x, y, (0.0, -1.0), EMINENCE_RIDGE_SIGMA_MM)
        # Smooth maximum (4-norm): two distinct tubercles on a ridge, no creases.
        return h + (medial ** 4 + lateral ** 4 + ridge ** 4) ** 0.25

    def distal_height(self, x: Array, y: Array) -> Array:
        """Distal articular end: vaulted plafond and the medial malleolus."""
        u, v = self.to_distal_local(x, y)
        plafond = (self.z_tip + PLAFOND_HEIGHT_MM
                   + PLAFOND_VAULT_MM * _bump(u, v, (0.0, 0.0), PLAFOND_VAULT_SEMI_AXES))
        q = (((u - MEDIAL_MALLEOLUS_TIP[0]) / MEDIAL_MALLEOLUS_SEMI_AXES[0]) ** 2
             + ((v - MEDIAL_MALLEOLUS_TIP[1]) / MEDIAL_MALLEOLUS_SEMI_AXES[1]) ** 2)
        malleolus = self.z_tip + PLAFOND_HEIGHT_MM * q ** MEDIAL_MALLEOLUS_BLUNTNESS
        return _smin(plafond, malleolus, DISTAL_BLEND_MM)

    # --- fibula -------------------------------------------------------------

    def _fibula_distal_xy_local(self, height: Array) -> tuple[Array, Array]:
        """Fibula centre line in the distal tibial frame (height above tip)."""
        h, x, y = np.array(FIBULA_DISTAL_CENTRE_LINE).T[:, ::-1]
        return np.interp(height, h, x), np.interp(height, h, y)

    def _build_fibula_curves(self) -> None:
        """Centre line and section profile of the fibula as smooth curves of z."""
        L = self.length
        prox = np.array(FIBULA_PROXIMAL_CENTRE_LINE)
        dist = np.array(FIBULA_DISTAL_CENTRE_LINE)
        dx, dy = _rotate(dist[:, 1], dist[:, 2], self.torsion)
        dx, dy = dx + self.distal_centre[0], dy + self.distal_centre[1]
        mid_z = -0.5 * L
        mid = 0.5 * (prox[-1, 1:] + np.array([dx[0], dy[0]])) + FIBULA_MID_BOW_MM
        z = np.concatenate([-prox[:, 0], [mid_z], self.z_tip + dist[:, 0]])
        xy = np.concatenate([prox[:, 1:], [mid], np.stack([dx, dy], axis=1)])
        order = np.argsort(z)
        self._fib_centre = PchipInterpolator(z[order], xy[order], axis=0)

        pp = np.array(FIBULA_PROXIMAL_PROFILE)
        dp = np.array(FIBULA_DISTAL_PROFILE)
        pz = np.concatenate([-pp[:, 0], self.z_tip + dp[:, 0]])
        profile = np.concatenate([pp[:, 1:], dp[:, 1:]])
        order = np.argsort(pz)
        self._fib_profile = PchipInterpolator(pz[order], profile[order], axis=0)

        self.fib_top_rim = -FIBULA_HEAD_TOP_MM - FIBULA_HEAD_DOME_MM
        self.fib_bottom_rim = self.z_tip - LATERAL_MALLEOLUS_DROP_MM + LATERAL_MALLEOLUS_DOME_MM

    def fibula_centre(self, z: Array) -> tuple[Array, Array]:
        """Centre line of the fibula (anatomical frame, mm)."""
        c = self._fib_centre(np.clip(z, self.fib_bottom_rim, self.fib_top_rim))
        return c[..., 0], c[..., 1]

    def fibula_radius(self, cos_t: Array, sin_t: Array, z: Array) -> Array:
        """Polar radius (mm) of the fibula section in direction (cos_t, sin_t).

        An ellipse (ML, AP semi-axes) with a slight triangular shaft (crests
        anterior, posteromedial, posterolateral); it turns with the tibial
        torsion. Algebraic in the direction, as it is evaluated very often.
        """
        prof = self._fib_profile(np.clip(z, self.fib_bottom_rim, self.fib_top_rim))
        a, b, tri = prof[..., 0], prof[..., 1], prof[..., 2]
        twist = self.twist(z)
        c = cos_t * np.cos(twist) + sin_t * np.sin(twist)   # direction in the
        s = sin_t * np.cos(twist) - cos_t * np.sin(twist)   # twisted section
        r = a * b / np.sqrt((b * c) ** 2 + (a * s) ** 2)
        return r * (1.0 - tri * (3.0 * s - 4.0 * s ** 3))  # cos(3(phi - 90deg))

    def fibula_dome_scale(self, z: Array) -> Array:
        """Section shrink factor in the rounded end domes (0 beyond the ends)."""
        above = np.clip((z - self.fib_top_rim) / FIBULA_HEAD_DOME_MM, 0.0, 1.0)
        below = np.clip((self.fib_bottom_rim - z) / LATERAL_MALLEOLUS_DOME_MM, 0.0, 1.0)
        return np.sqrt(np.clip(1.0 - np.maximum(above, below) ** 2, 0.0, None))

    def fibula_sdf(self, x: Array, y: Array, z: Array) -> Array:
        """Approximate signed distance to the fibula section at height z.

        Exact polar radius only near the fibula; elsewhere a lower bound of the
        distance is returned, which is all the tibial carving needs (it only
        acts within a few mm) and keeps the build fast.
        """
        cx, cy = self.fibula_centre(z)
        dx, dy = x - cx, y - cy
        rho = np.maximum(np.hypot(dx, dy), 1e-9)
        prof = self._fib_profile(np.clip(z, self.fib_bottom_rim, self.fib_top_rim))
        bound = (np.maximum(prof[..., 0], prof[..., 1]) * (1.0 + np.abs(prof[..., 2]))
                 * self.fibula_dome_scale(z))
        dist = rho - bound
        near = dist < FIBULA_EXACT_DISTANCE_MM
        z_near = np.broadcast_to(z, rho.shape)[near]
        radius = (self.fibula_radius(dx[near] / rho[near], dy[near] / rho[near], z_near)
                  * self.fibula_dome_scale(z_near))
        dist[near] = rho[near] - radius
        return dist

    def fibula_clearance_sdf(self, x: Array, y: Array, z: Array) -> Array:
        """Distance to the fibula within a small height window around z.

        The window covers the spacing between tibia rings (so the lofted
        surface between two rings keeps clear of the fibular head apex) and,
        distally, every fibula section below z: the tibial walls near the
        plafond are vertical and must clear the whole lateral malleolus.
        """
        reach = (DISTAL_WALL_MM + LATERAL_MALLEOLUS_DROP_MM) * _smoothstep(
            self.z_tip + 2.0 * DISTAL_WALL_MM, self.z_bottom_wall, z)
        samples = 3 if not np.any(reach > 0.0) else 11
        offsets = np.linspace(FIBULA_CLEARANCE_WINDOW_MM,
                              -FIBULA_CLEARANCE_WINDOW_MM - reach, samples)
        return np.min([self.fibula_sdf(x, y, z + dz) for dz in offsets], axis=0)


# ---------------------------------------------------------------------------
# Mesh assembly.


def _sphere_grid_faces(n_rings: int, n_around: int) -> Array:
    """Faces of a closed grid: top pole, n_rings rings (top to bottom), bottom pole.

    Rings run counter-clockwise seen from +z, so faces point outward.
    """
    k = np.arange(n_around)
    k1 = (k + 1) % n_around
    ring = 1 + np.arange(n_rings - 1)[:, None] * n_around
    a, b = ring + k, ring + k1
    c, d = b + n_around, a + n_around
    sides = np.concatenate([np.stack([a, d, c], -1), np.stack([a, c, b], -1)]).reshape(-1, 3)
    top = np.stack([np.zeros_like(k), 1 + k, 1 + k1], -1)
    last = 1 + (n_rings - 1) * n_around
    bottom_pole = last + n_around
    bottom = np.stack([np.full_like(k, bottom_pole), last + k1, last + k], -1)
    return np.concatenate([top, sides, bottom])


def _radial_hull(sdf: Callable[[Array, Array, Array], Array], cx: Array, cy: Array,
                 z: Array, theta: Array, r_max: float = 50.0, step: float = 2.0,
                 iterations: int = 14) -> Array:
    """Outermost zero crossing of sdf along horizontal rays from (cx, cy, z).

    cx, cy, z: (R,) ring centres/heights; theta: (N,). Returns radii (R, N).
    """
    ux, uy = np.cos(theta)[None, :], np.sin(theta)[None, :]
    cx, cy, zz = cx[:, None], cy[:, None], z[:, None]
    t = np.arange(0.0, r_max + step, step)[:, None, None]
    inside = sdf(cx + t * ux, cy + t * uy, zz) < 0.0
    if inside[-1].any() or not inside[0].all():
        raise RuntimeError("phantom section is not inside the ray-casting range")
    last_inside = len(t) - 1 - np.argmax(inside[::-1], axis=0)
    lo = last_inside * step
    hi = lo + step
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        is_in = sdf(cx + mid * ux, cy + mid * uy, zz) < 0.0
        lo, hi = np.where(is_in, mid, lo), np.where(is_in, hi, mid)
    return 0.5 * (lo + hi)


def _tibia_wall_spacing(design: _RightLegDesign) -> Callable[[Array], Array]:
    """Ring spacing (mm) along z: dense at the metaphyses, sparse on the shaft."""
    L = design.length
    depths = [0.0, 30.0, 90.0, 130.0, L - 120.0, L - 70.0, L]
    spacing = [1.5, 2.0, 3.0, 9.0, 9.0, 3.0, 2.0]
    return lambda z: np.interp(-z, depths, spacing)


def _build_tibia(design: _RightLegDesign) -> trimesh.Trimesh:
    """Loft the tibia: plateau cap, walls, distal cap; one closed grid."""
    n = TIBIA_RING_VERTICES
    theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    ux, uy = np.cos(theta), np.sin(theta)

    z_walls = _ring_heights(design.z_top_wall, design.z_bottom_wall,
                            _tibia_wall_spacing(design))
    cx, cy = design.ray_centre(z_walls)
    # The fibula only comes close to the tibia at the two tibiofibular joints
    # (head under the lateral condyle, distal syndesmosis); elsewhere the costly
    # carving is skipped. Each group is cast separately so that the windowed
    # distal clearance is only computed where needed.
    proximal = z_walls > -METAPHYSIS_END_MM
    distal = z_walls < design.z_tip + DISTAL_FLARE_START_MM
    radii = np.empty((len(z_walls), n))
    for rows, carve in ((proximal, True), (distal, True), (~(proximal | distal), False)):
        radii[rows] = _radial_hull(partial(design.tibia_sdf, carve=carve),
                                   cx[rows], cy[rows], z_walls[rows], theta)

    def cap(ring_radius: Array, centre: tuple[float, float], pole_xy: tuple[float, float],
            height: Callable[[Array, Array], Array], edge: float, sign: float,
            n_cap: int) -> tuple[Array, Array]:
        """Cap rings from pole to rim: height field, then a rounded edge.

        The rim follows the wall rays from centre; the inner rings shrink
        towards pole_xy, which must see the whole rim (star-shaped cap).
        sign=+1 for the plateau (edge rolls down), -1 for the distal end.
        Returns the pole (3,) and rings (n_cap + EDGE_ROUND_RINGS, n, 3).
        """
        inner = np.clip(ring_radius - edge, 0.5, None)
        rim = np.stack([centre[0] + inner * ux - pole_xy[0],
                        centre[1] + inner * uy - pole_xy[1]], axis=-1)
        nxt = np.roll(rim, -1, axis=0)
        if np.any(rim[:, 0] * nxt[:, 1] - rim[:, 1] * nxt[:, 0] <= 0.0):
            raise RuntimeError("cap pole does not see the whole rim")
        s = np.linspace(0.0, 1.0, n_cap + 1)[1:, None]
        phi = np.linspace(0.5 * np.pi, 0.0, EDGE_ROUND_RINGS + 1)[1:, None]
        roll = inner + edge * np.cos(phi)
        x = np.concatenate([pole_xy[0] + s * rim[:, 0], centre[0] + roll * ux])
        y = np.concatenate([pole_xy[1] + s * rim[:, 1], centre[1] + roll * uy])
        drop = np.concatenate([np.zeros_like(s), edge * (1.0 - np.sin(phi))])
        z = height(x, y) - sign * drop
        pole = np.array([*pole_xy, float(height(*map(np.asarray, pole_xy)))])
        return pole, np.stack([x, y, z], axis=-1)

    top_centre = (float(cx[0]), float(cy[0]))
    bottom_centre = (float(cx[-1]), float(cy[-1]))
    top_pole, top_rings = cap(radii[0], top_centre, TOP_CAP_POLE, design.plateau_height,
                              PLATEAU_EDGE_RADIUS_MM, 1.0, TOP_CAP_RINGS)
    bottom_pole, bottom_rings = cap(radii[-1], bottom_centre, bottom_centre,
                                    design.distal_height,
                                    DISTAL_EDGE_RADIUS_MM, -1.0, BOTTOM_CAP_RINGS)

    walls = np.stack([cx[:, None] + radii * ux, cy[:, None] + radii * uy,
                      np.broadcast_to(z_walls[:, None], radii.shape)], axis=-1)
    # Vertical transition rings between the (non-planar) cap rims and the
    # first/last planar wall ring.
    t = np.linspace(0.0, 1.0, RIM_TRANSITION_RINGS + 2)[1:-1, None]
    top_rim, bottom_rim = top_rings[-1], bottom_rings[-1]
    top_join = top_rim + t[..., None] * (walls[0] - top_rim)
    bottom_join = walls[-1] + t[..., None] * (bottom_rim - walls[-1])
    rings = np.concatenate([top_rings, top_join, walls, bottom_join, bottom_rings[::-1]])
    vertices = np.concatenate([top_pole[None], rings.reshape(-1, 3), bottom_pole[None]])
    return trimesh.Trimesh(vertices, _sphere_grid_faces(len(rings), n), process=False)


def _build_fibula(design: _RightLegDesign) -> trimesh.Trimesh:
    """Loft the fibula: head dome, curved shaft, lateral malleolus dome."""
    n = FIBULA_RING_VERTICES
    theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    L = design.length
    depths = [0.0, 60.0, 110.0, L - 110.0, L - 50.0, L + 20.0]
    spacing = [1.5, 2.5, 6.0, 6.0, 2.5, 1.5]
    z_walls = _ring_heights(design.fib_top_rim, design.fib_bottom_rim,
                            lambda z: np.interp(-z, depths, spacing))
    phi = np.linspace(0.0, 0.5 * np.pi, FIBULA_DOME_RINGS + 1)[1:-1]
    z_top = design.fib_top_rim + FIBULA_HEAD_DOME_MM * np.cos(phi)
    z_bottom = design.fib_bottom_rim - LATERAL_MALLEOLUS_DOME_MM * np.cos(phi[::-1])
    z = np.concatenate([z_top, z_walls, z_bottom])[:, None]
    cx, cy = design.fibula_centre(z)
    r = (design.fibula_radius(np.cos(theta), np.sin(theta), z)
         * design.fibula_dome_scale(z))
    rings = np.stack([cx + r * np.cos(theta), cy + r * np.sin(theta),
                      np.broadcast_to(z, r.shape)], axis=-1)
    poles = []
    for z_end in (design.fib_top_rim + FIBULA_HEAD_DOME_MM,
                  design.fib_bottom_rim - LATERAL_MALLEOLUS_DOME_MM):
        px, py = design.fibula_centre(np.array(z_end))
        poles.append([float(px), float(py), z_end])
    vertices = np.concatenate([[poles[0]], rings.reshape(-1, 3), [poles[1]]])
    return trimesh.Trimesh(vertices, _sphere_grid_faces(len(rings), n), process=False)


def _mirror_x(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Mirror a right-leg mesh to the left leg, keeping outward winding."""
    vertices = mesh.vertices * np.array([-1.0, 1.0, 1.0])
    return trimesh.Trimesh(vertices, mesh.faces[:, ::-1], process=False)


def phantom_plan(side: str = "right", target: Target = Target()) -> Plan:
    """The built-in parametric tibia and fibula as a plan, with the default trocar pin; the
    phantom is exact, so it carries no segmentation error."""
    bone = build_phantom(side)
    landmarks = Landmarks(bone.knee_centre, bone.ankle_centre, bone.anterior, side)
    spec = PinSpec()
    return Plan(Surface.of(bone.tibia), Surface.of(bone.fibula), landmarks, build_pin(spec), spec,
                target, "PHANTOM", segmentation_sd_mm=0.0)

