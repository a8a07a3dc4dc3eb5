"""Tests of the built-in parametric tibia + fibula phantom (solver/phantom.py).

The phantom must be a valid closed mesh, sit in the documented anatomical
frame, have adult dimensions, and, above all, not be rotationally symmetric:
2D-3D registration on it must be as well posed as on real bone.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from slamtka.sim.bone_phantom import PhantomBone, build_phantom

LENGTH_MM = 370.0


@pytest.fixture(scope="module")
def right() -> PhantomBone:
    return build_phantom("right", LENGTH_MM)


@pytest.fixture(scope="module")
def left() -> PhantomBone:
    return build_phantom("left", LENGTH_MM)


@pytest.fixture(scope="module", params=["right", "left"])
def bone(request: pytest.FixtureRequest, right: PhantomBone, left: PhantomBone) -> PhantomBone:
    return right if request.param == "right" else left


def _section_points(mesh: trimesh.Trimesh, z: float) -> np.ndarray:
    """(n, 2) points on the contour of the horizontal cross-section at height z."""
    segments = trimesh.intersections.mesh_plane(mesh, [0.0, 0.0, 1.0], [0.0, 0.0, z])
    assert len(segments) > 0, f"no cross-section at z={z}"
    return segments.reshape(-1, 3)[:, :2]


def _radial_profile(points: np.ndarray, n: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """Contour radius around its centroid sampled at n angles (star-shaped sections)."""
    centre = points.mean(axis=0)
    d = points - centre
    angle, radius = np.arctan2(d[:, 1], d[:, 0]), np.hypot(d[:, 0], d[:, 1])
    order = np.argsort(angle)
    grid = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return grid, np.interp(grid, angle[order], radius[order], period=2.0 * np.pi)


def _silhouette_widths(meshes: list[trimesh.Trimesh], view_deg: float,
                       pixel_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Filled-triangle silhouette seen horizontally from view_deg around z.

    view_deg = 0 looks from anterior (AP), 90 from the patient's right.
    Returns the silhouette width (mm) of every image row and the row heights z.
    """
    a = np.radians(view_deg)
    screen = np.array([np.cos(a), -np.sin(a), 0.0])   # perpendicular to the view
    points = np.concatenate([m.vertices for m in meshes])
    u0, z_top = (points @ screen).min() - 2.0, points[:, 2].max() + 2.0
    width = int(((points @ screen).max() + 2.0 - u0) / pixel_mm) + 1
    height = int((z_top - points[:, 2].min() + 2.0) / pixel_mm) + 1
    mask = np.zeros((height, width), np.uint8)
    for mesh in meshes:
        uv = np.stack([(mesh.vertices @ screen - u0) / pixel_mm,
                       (z_top - mesh.vertices[:, 2]) / pixel_mm], axis=-1)
        for triangle in np.round(uv[mesh.faces] * 16).astype(np.int32):
            cv2.fillConvexPoly(mask, triangle, 1, shift=4)
    rows_z = z_top - np.arange(height) * pixel_mm
    return mask.sum(axis=1) * pixel_mm, rows_z


# --- mesh validity -----------------------------------------------------------


def test_meshes_are_closed_outward_and_moderate(bone: PhantomBone) -> None:
    for mesh in (bone.tibia, bone.fibula):
        assert mesh.is_watertight
        assert mesh.is_winding_consistent
        assert mesh.volume > 0.0
        # outward normals: at the extreme faces along +-x, +-y, +-z the normal
        # points away from the bone
        centres, normals = mesh.triangles_center, mesh.face_normals
        for axis in range(3):
            assert normals[np.argmax(centres[:, axis]), axis] > 0.5
            assert normals[np.argmin(centres[:, axis]), axis] < -0.5
    assert 10_000 <= len(bone.tibia.faces) <= 40_000
    assert 3_000 <= len(bone.fibula.faces) <= 15_000
    # adult volumes (cm^3): tibia ~ 200-400, fibula ~ 30-90
    assert 200e3 < bone.tibia.volume < 400e3
    assert 30e3 < bone.fibula.volume < 90e3


def test_no_degenerate_or_spiky_triangles(right: PhantomBone) -> None:
    for mesh in (right.tibia, right.fibula):
        assert mesh.area_faces.min() > 1e-6
        assert mesh.edges_unique_length.max() < 12.0
        # adjacent faces never fold sharply (no spikes or creases)
        assert np.degrees(mesh.face_adjacency_angles.max()) < 90.0


def test_fibula_touches_but_does_not_penetrate_tibia(bone: PhantomBone) -> None:
    overlap = trimesh.boolean.intersection([bone.tibia, bone.fibula], engine="manifold")
    overlap_volume = 0.0 if overlap.is_empty else overlap.volume
    assert overlap_volume < 0.001 * bone.fibula.volume
    # ... yet they articulate: nearly in contact at both tibiofibular joints
    tibia = cKDTree(bone.tibia.vertices)
    fibula = bone.fibula.vertices
    head = fibula[fibula[:, 2] > -40.0]
    distal = fibula[fibula[:, 2] < -LENGTH_MM + 40.0]
    shaft = fibula[(fibula[:, 2] < -120.0) & (fibula[:, 2] > -220.0)]
    assert tibia.query(head)[0].min() < 3.5
    assert tibia.query(distal)[0].min() < 3.5
    assert tibia.query(shaft)[0].min() > 5.0   # interosseous space mid-shaft


def test_deterministic() -> None:
    a, b = build_phantom("right", 380.0), build_phantom("right", 380.0)
    assert np.array_equal(a.tibia.vertices, b.tibia.vertices)
    assert np.array_equal(a.fibula.vertices, b.fibula.vertices)



# --- frame, landmarks and dimensions ------------------------------------------


@pytest.mark.parametrize("length", [350.0, 370.0, 400.0])
def test_length_and_landmarks(length: float) -> None:
    bone = build_phantom("right", length)
    z = bone.tibia.vertices[:, 2]
    # plateau articular level (z = 0) to the medial malleolus tip
    assert z.min() == pytest.approx(-length, abs=0.5)
    assert 349.5 <= -z.min() <= 400.5   # mesh tip within 0.5 mm of the design
    assert 6.0 <= np.ptp(z) - length <= 12.0   # + intercondylar eminence
    np.testing.assert_allclose(bone.knee_centre, 0.0)
    np.testing.assert_allclose(bone.anterior, [0.0, 1.0, 0.0])
    ankle = bone.ankle_centre
    np.testing.assert_allclose(ankle[:2], 0.0, atol=1e-6)
    assert length - 10.0 < -ankle[2] < length


def test_ankle_centre_is_between_the_malleoli(bone: PhantomBone) -> None:
    sign = 1.0 if bone.side == "right" else -1.0
    tibia, fibula = bone.tibia.vertices, bone.fibula.vertices
    level = bone.ankle_centre[2]
    medial = tibia[np.abs(tibia[:, 2] - level) < 2.0]
    lateral = fibula[np.abs(fibula[:, 2] - level) < 2.0]
    # medial malleolus on the medial side, lateral malleolus on the lateral side
    assert sign * medial[:, 0].max() < 0.0 < sign * lateral[:, 0].min()
    midpoint = 0.5 * (medial.mean(axis=0) + lateral.mean(axis=0))
    np.testing.assert_allclose(midpoint[:2], 0.0, atol=2.0)


def test_plateau_dimensions_and_surface(right: PhantomBone) -> None:
    v = right.tibia.vertices
    plateau = v[v[:, 2] > -8.0]
    assert 70.0 <= np.ptp(plateau[:, 0]) <= 80.0   # mediolateral width
    assert 44.0 <= np.ptp(plateau[:, 1]) <= 52.0   # anteroposterior depth
    # intercondylar eminence: the highest point, 6-12 mm, between the condyles
    top = v[np.argmax(v[:, 2])]
    assert 6.0 <= top[2] <= 12.0 and abs(top[0]) < 10.0
    # medial condyle surface is concave: lower at its centre than at its rim
    medial_centre = v[(np.hypot(v[:, 0] + 18.0, v[:, 1] + 1.0) < 3.0) & (v[:, 2] > -6.0)]
    medial_rim = v[(np.abs(v[:, 0] + 30.0) < 2.0) & (np.abs(v[:, 1]) < 3.0) & (v[:, 2] > -6.0)]
    assert medial_centre[:, 2].max() < medial_rim[:, 2].max() - 0.5


def test_plateau_is_kidney_shaped(right: PhantomBone) -> None:
    """Posterior intercondylar notch: the outline is concave posteriorly."""
    section = _section_points(right.tibia, -6.0)
    posterior_edge = section[:, 1].min()
    x_mid = np.median(section[:, 0])
    notch = section[(np.abs(section[:, 0] - x_mid) < 3.0) & (section[:, 1] < 0.0)]
    assert notch[:, 1].min() - posterior_edge > 4.0


def test_tuberosity_protrudes_anteriorly(right: PhantomBone) -> None:
    v = right.tibia.vertices
    plateau_front = v[v[:, 2] > -6.0, 1].max()
    tuberosity = v[(v[:, 2] < -20.0) & (v[:, 2] > -50.0)]
    front = tuberosity[np.argmax(tuberosity[:, 1])]
    assert front[1] > plateau_front + 1.0
    assert -2.0 < front[0] < 12.0   # midline to slightly lateral


def test_distal_tibia_and_medial_malleolus(bone: PhantomBone) -> None:
    sign = 1.0 if bone.side == "right" else -1.0
    v = bone.tibia.vertices
    distal = _section_points(bone.tibia, -LENGTH_MM + 16.0)
    assert 42.0 <= np.ptp(distal[:, 0]) <= 52.0
    tip = v[np.argmin(v[:, 2])]
    assert sign * tip[0] < -10.0    # lowest tibial point is medial
    lateral_half = v[sign * v[:, 0] > sign * distal[:, 0].mean()]
    projection = lateral_half[:, 2].min() - tip[2]
    assert 8.0 <= projection <= 18.0   # malleolus projects beyond the plafond


def test_fibula_position_and_size(bone: PhantomBone) -> None:
    sign = 1.0 if bone.side == "right" else -1.0
    fibula, tibia = bone.fibula.vertices, bone.tibia.vertices
    centroid = bone.fibula.center_mass
    assert sign * centroid[0] > 10.0      # lateral
    assert centroid[1] < 0.0              # posterior to the tibial axis
    assert -20.0 <= fibula[:, 2].max() <= -8.0          # head just below plateau
    drop = tibia[:, 2].min() - fibula[:, 2].min()
    assert 10.0 <= drop <= 20.0                         # lateral malleolus lower
    head = _section_points(bone.fibula, -24.0)
    assert 20.0 <= np.ptp(head[:, 0]) <= 30.0
    for z in (-120.0, -185.0, -250.0):
        shaft = _section_points(bone.fibula, z)
        assert 10.0 <= np.ptp(shaft[:, 0]) <= 16.0
        assert sign * shaft[:, 0].mean() > 15.0


def test_external_tibial_torsion(bone: PhantomBone) -> None:
    """Lateral malleolus is posterior to the medial one (bimalleolar axis)."""
    tibia, fibula = bone.tibia.vertices, bone.fibula.vertices
    medial = tibia[np.argmin(tibia[:, 2])]
    lateral = fibula[np.argmin(fibula[:, 2])]
    axis = lateral - medial
    angle = np.degrees(np.arctan2(-axis[1], abs(axis[0])))
    assert 10.0 <= angle <= 40.0


# --- side handling --------------------------------------------------------------


def test_left_is_mirror_of_right(right: PhantomBone, left: PhantomBone) -> None:
    assert right.side == "right" and left.side == "left"
    for r_mesh, l_mesh in ((right.tibia, left.tibia), (right.fibula, left.fibula)):
        mirrored = r_mesh.vertices * np.array([-1.0, 1.0, 1.0])
        a = mirrored[np.lexsort(mirrored.T)]
        b = l_mesh.vertices[np.lexsort(l_mesh.vertices.T)]
        np.testing.assert_allclose(a, b, atol=1e-9)
        assert l_mesh.volume == pytest.approx(r_mesh.volume)
    np.testing.assert_allclose(left.ankle_centre, right.ankle_centre * [-1.0, 1.0, 1.0])
    np.testing.assert_allclose(left.anterior, right.anterior)


@pytest.mark.parametrize("side", ["middle", "Right", "", "l"])
def test_bad_side_raises(side: str) -> None:
    with pytest.raises(ValueError, match="side"):
        build_phantom(side)


@pytest.mark.parametrize("length", [349.9, 400.1, 0.0, -370.0, float("nan")])
def test_bad_length_raises(length: float) -> None:
    with pytest.raises(ValueError, match="length_mm"):
        build_phantom("right", length)


# --- not rotationally symmetric -----------------------------------------------------


def test_silhouettes_differ_between_views(right: PhantomBone) -> None:
    meshes = [right.tibia, right.fibula]
    heights = np.arange(-LENGTH_MM, 0.0, 1.0)
    profiles = {}
    for view in range(0, 180, 30):   # orthographic: 180 deg apart look alike
        widths, z = _silhouette_widths(meshes, float(view))
        profiles[view] = np.interp(heights, z[::-1], widths[::-1])
    proximal = heights > -60.0
    ap, lateral = profiles[0][proximal].mean(), profiles[90][proximal].mean()
    assert ap > 1.2 * lateral                    # plateau is wide, not deep
    assert 65.0 < ap < 85.0 and 40.0 < lateral < 60.0
    # every view differs from every other one along the whole leg
    for a in profiles:
        for b in profiles:
            if a < b:
                assert np.abs(profiles[a] - profiles[b]).mean() > 1.5, (a, b)


def test_midshaft_section_is_triangular(bone: PhantomBone) -> None:
    section = _section_points(bone.tibia, -0.5 * LENGTH_MM)
    assert 20.0 <= np.ptp(section[:, 0]) <= 30.0   # ~25 mm mediolateral
    angles, radius = _radial_profile(section)
    assert (radius.max() - radius.min()) / radius.mean() > 0.3   # far from a circle
    directions = np.linspace(0.0, np.pi, 90, endpoint=False)
    calipers = [np.ptp(section @ [np.cos(t), np.sin(t)]) for t in directions]
    assert max(calipers) / min(calipers) > 1.1
    # three corners: the smoothed radial profile has three maxima and its
    # third harmonic dominates
    spectrum = np.fft.rfft(radius)
    assert np.argmax(np.abs(spectrum[1:7])) + 1 == 3
    spectrum[6:] = 0.0
    smooth = np.fft.irfft(spectrum, len(radius))
    peaks = np.flatnonzero((smooth > np.roll(smooth, 1)) & (smooth >= np.roll(smooth, -1)))
    assert len(peaks) == 3
    # one corner is the anterior crest
    assert np.min(np.abs(np.degrees(angles[peaks]) - 90.0)) < 25.0


def test_shaft_narrowest_in_distal_third(right: PhantomBone) -> None:
    heights = np.linspace(-100.0, -LENGTH_MM + 60.0, 40)
    widths = [np.ptp(_section_points(right.tibia, z)[:, 0]) for z in heights]
    narrowest = heights[int(np.argmin(widths))]
    assert -0.8 * LENGTH_MM < narrowest < -0.55 * LENGTH_MM
