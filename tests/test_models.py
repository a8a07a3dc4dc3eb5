import logging
from concurrent.futures import ThreadPoolExecutor

import igl
import numpy as np
import pytest
import trimesh
from conftest import SHARED_DATA

from slamtka.sim.simulate import default_camera
from slamtka.solver.geometry import Pose
from slamtka.solver.meshes import MeshError, load_mesh
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.sdf import SignedDistanceField
from slamtka.solver.surface import Surface


def test_pin_is_a_closed_trocar_of_the_right_size():
    pin = build_pin(PinSpec(length_mm=80.0))
    assert pin.to_trimesh().is_watertight and pin.to_trimesh().volume > 0
    assert np.allclose(pin.bounds, [[-1.6, -1.6, 0.0], [1.6, 1.6, 80.0]], atol=1e-6)
    tip = pin.vertices[pin.vertices[:, 2] < 5.0]
    # Three facets: the tip cross-section at mid height is a rounded triangle, not a circle.
    ring = tip[np.abs(tip[:, 2] - tip[:, 2].max() / 2) < 0.6]
    assert len(ring) > 0
    with pytest.raises(ValueError):
        PinSpec(diameter_mm=40.0)


def test_pin_shadows_are_as_wide_and_long_as_the_pin_projected(phantom_plan):
    """Pins across the beam at 500 mm: a shadow fx * d / z wide and fx * L / z long; the
    same pins along the beam: end-on, a shadow no longer than it is wide."""
    camera, length = default_camera(), phantom_plan.pin_length()
    across = Pose(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
                  [-0.5 * length, 0.0, 500.0])
    shadows = phantom_plan.pin_shadows(camera, Pose.identity(), [across, across])
    assert shadows.width_px == pytest.approx(camera.fx * phantom_plan.pin_diameter() / 500.0)
    assert shadows.length_px == pytest.approx(camera.fx * length / 500.0, rel=1e-6)
    along = Pose(np.eye(3), [0.0, 0.0, 500.0 - 0.5 * length])
    end_on = phantom_plan.pin_shadows(camera, Pose.identity(), [along, along])
    assert end_on.length_px < end_on.width_px


def test_sdf_matches_exact_distance_and_its_gradient(tmp_path):
    pin = build_pin()
    field = SignedDistanceField.cached([pin], 0.2, 1.6, tmp_path)
    assert len(list(tmp_path.glob("sdf-*.npz"))) == 1
    again = SignedDistanceField.cached([pin], 0.2, 1.6, tmp_path)
    assert np.array_equal(again.values, field.values)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-3, 3, 500), rng.uniform(10, 80, 500)])
    exact = igl.signed_distance(pts, pin.vertices.astype(float), pin.faces.astype(np.int64))[0]
    value, grad = field.query(pts)
    assert np.median(np.abs(value - exact)) < 0.03
    eps = 1e-5
    for axis in range(3):
        d = np.zeros(3)
        d[axis] = eps
        fd = (field.query(pts + d)[0] - field.query(pts - d)[0]) / (2 * eps)
        assert np.median(np.abs(fd - grad[:, axis])) < 1e-4
    # Far outside the grid the distance keeps growing and points back.
    far_value, far_grad = field.query(np.array([[30.0, 0.0, 40.0]]))
    assert far_value[0] > 25 and far_grad[0, 0] > 0.9
    # Distances alone (ray searches, trial steps) are the same values.
    assert np.array_equal(field.query(pts, gradient=False)[0], value)
    assert field.query(pts, gradient=False)[1] is None


def test_sdf_cache_entry_written_by_several_workers_at_once(tmp_path):
    """Parallel workers building one plan write the same entry together: none may fail or
    leave a temporary file, and the entry reads back whole."""
    field = SignedDistanceField.build([build_pin()], 0.4, 1.6)
    path = tmp_path / "sdf-shared.npz"
    with ThreadPoolExecutor(8) as pool:
        list(pool.map(lambda _: field.save(path), range(16)))
    assert [p.name for p in tmp_path.iterdir()] == ["sdf-shared.npz"]
    assert np.array_equal(SignedDistanceField.load(path).values, field.values)


@pytest.mark.skipif(not (SHARED_DATA / "tibia-right.stl").exists(), reason="shared meshes absent")
def test_real_meshes_in_metres_are_converted_and_holes_reported(caplog):
    with caplog.at_level(logging.WARNING):
        tibia = load_mesh(SHARED_DATA / "tibia-right.stl", (40.0, 600.0))
        fibula = load_mesh(SHARED_DATA / "fibula-right.stl", (40.0, 600.0))
    assert 80 < tibia.extents.max() < 95
    assert fibula.extents.max() > 40
    assert "units detected as m" in caplog.text and "not watertight" in caplog.text
    with pytest.raises(MeshError, match="not watertight"):
        load_mesh(SHARED_DATA / "fibula-right.stl", (40.0, 600.0), require_watertight=True)


def test_bad_mesh_files_get_clear_errors(tmp_path):
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    with pytest.raises(MeshError, match="empty.stl"):
        load_mesh(empty, (40, 600))
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("this is not a mesh\n")
    with pytest.raises(MeshError, match="garbage.obj"):
        load_mesh(garbage, (40, 600))
    text = tmp_path / "mesh.txt"
    text.write_text("")
    with pytest.raises(MeshError, match="unsupported"):
        load_mesh(text, (40, 600))
    huge = tmp_path / "huge.stl"
    trimesh.creation.box((5000, 5000, 5000)).export(huge)
    with pytest.raises(MeshError, match="fits no unit"):
        load_mesh(huge, (40, 600))
    with pytest.raises(MeshError, match="outside the plausible"):
        load_mesh(huge, (40, 600), units="mm")


def _covered_pixel_centres(generator, T_cam_model, camera, pixels: np.ndarray) -> np.ndarray:
    """Brute force: which footprint pixel centres (N, 2) lie in some front-facing face."""
    front = generator._front_facing(T_cam_model.inverse().t)
    tri = camera.project(T_cam_model.apply(generator.vertices))[generator.faces[front]] / 4.0
    a, b, c = (tri[None, :, k] for k in range(3))
    p = pixels[:, None, :].astype(float)

    def side(u, v):
        return (v[..., 0] - u[..., 0]) * (p[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (p[..., 0] - u[..., 0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return np.any(((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0)), axis=1)


@pytest.mark.parametrize("open_mesh", [False, True])
def test_footprint_is_the_union_of_front_faces(open_mesh):
    """The footprint rasterised from the outline's winding number is exactly the union of the
    front-facing faces at pixel centres, for closed meshes and for open ones (a mesh with a
    hole is bounded there by its open edges)."""
    from slamtka.solver.camera import Camera
    from slamtka.solver.geometry import look_at
    from slamtka.solver.silhouette import ContourGenerator

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.box([30.0, 120.0, 30.0])])
    if open_mesh:
        # Remove the faces on one side: the sphere shows a hole in the middle of its footprint.
        mesh.update_faces(mesh.triangles_center[:, 2] < 30.0)
    generator = ContourGenerator.from_mesh(mesh)
    camera = Camera(fx=4500.0, fy=4500.0, cx=512.0, cy=512.0, width=1024, height=1024)
    T_cam_model = look_at(np.array([20.0, -10.0, 700.0]), np.zeros(3), np.array([0.0, 1.0, 0.0])).inverse()
    mask = generator.footprint(T_cam_model, camera)
    rows, cols = np.nonzero(np.ones_like(mask))
    sample = np.random.default_rng(0).choice(len(rows), 20000, replace=False)
    pixels = np.column_stack([cols[sample], rows[sample]])
    expected = _covered_pixel_centres(generator, T_cam_model, camera, pixels)
    found = mask[pixels[:, 1], pixels[:, 0]] == 1
    assert expected.sum() > 1000
    assert np.mean(found == expected) > 0.995  # pixel centres exactly on an edge may go either way


def test_sdf_is_built_in_bounded_slabs_with_the_same_values(monkeypatch):
    """Building samples a bounded number of grid points at once (the build's peak memory),
    and the slabs add up to the field of one pass over the grid."""
    import slamtka.solver.sdf as sdf_module

    pin = build_pin()
    whole = SignedDistanceField.build([pin], 0.2, 1.6)
    sampled: list[int] = []
    exact = sdf_module._exact_signed_distance

    def spy(points, meshes, band_mm):
        sampled.append(len(points))
        return exact(points, meshes, band_mm)

    monkeypatch.setattr(sdf_module, "_exact_signed_distance", spy)
    monkeypatch.setattr(sdf_module, "_SLAB_POINTS", 20_000)
    slabbed = SignedDistanceField.build([pin], 0.2, 1.6)
    assert whole.values.size > 10 * 20_000 and max(sampled) <= 20_000
    np.testing.assert_allclose(slabbed.values, whole.values, atol=1e-5)


@pytest.mark.parametrize("spec", [PinSpec(), PinSpec(2.0, 60.0, 3.0), PinSpec(6.0, 250.0, 20.0)])
def test_the_pin_is_built_as_trimesh_would_process_it(spec):
    """The pin's arrays are built without trimesh (a solve never imports it): they are
    already what trimesh's processing (merging, removing degenerate faces) would leave."""
    pin = build_pin(spec)
    processed = trimesh.Trimesh(pin.vertices, pin.faces, process=True)
    assert np.array_equal(processed.vertices, pin.vertices) and np.array_equal(processed.faces, pin.faces)
    assert processed.is_watertight and processed.volume > 0


def test_silhouette_topology_is_stored_beside_the_plan(tmp_path, monkeypatch):
    """A plan's load in the operating room reads its silhouette topology, never decimates
    or looks for each edge's faces."""
    from slamtka.solver.plan import RigidModel
    from slamtka.solver.silhouette import ContourGenerator, simplified

    sphere = Surface.of(trimesh.creation.icosphere(subdivisions=6, radius=20.0))  # 81920 faces
    model = RigidModel.build("ball", [sphere], 2.0, tmp_path)
    assert len(model.contour.faces) <= 6000 and len(model.coarse_contour.faces) <= 1500
    assert len(list(tmp_path.glob("silhouettes-*.npz"))) == 1
    fine = simplified(sphere.to_trimesh(), 6000)
    expected = ContourGenerator.from_mesh(fine), ContourGenerator.from_mesh(simplified(fine, 1500))

    def refuse(*args, **kwargs):
        raise AssertionError("built again although the plan's cache holds it")

    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", refuse)
    monkeypatch.setattr(ContourGenerator, "from_mesh", refuse)
    again = RigidModel.build("ball", [sphere], 2.0, tmp_path)
    for stored, built in zip((again.contour, again.coarse_contour), expected):
        for name, array in built.arrays("").items():
            np.testing.assert_array_equal(getattr(stored, name), array)


def test_sdf_query_matches_the_trilinear_interpolant_inside_and_beyond_the_grid():
    """The compiled lookup is the trilinear interpolant of the grid, plus the distance to
    the grid outside it (written here with plain numpy, one corner at a time)."""
    rng = np.random.default_rng(5)
    values = rng.normal(size=(4, 5, 6)).astype(np.float32)
    field = SignedDistanceField(np.array([1.0, -2.0, 0.5]), 0.5, values, "")
    points = rng.uniform([0.0, -3.0, -0.5], [3.5, 1.0, 4.5], (400, 3))  # some beyond the grid
    g = (points - field.origin) / field.spacing
    clamped = np.clip(g, 0.0, np.array(values.shape) - 1 - 1e-9)
    i, f = np.floor(clamped).astype(int), clamped - np.floor(clamped)
    expected = np.zeros(len(points))
    for corner in np.ndindex(2, 2, 2):
        weight = np.prod(np.where(np.array(corner) == 1, f, 1 - f), axis=1)
        expected += weight * values[i[:, 0] + corner[0], i[:, 1] + corner[1], i[:, 2] + corner[2]]
    expected += np.linalg.norm((g - clamped) * field.spacing, axis=1)
    value, grad = field.query(points)
    np.testing.assert_allclose(value, expected, atol=1e-6)
    assert grad.shape == (len(points), 3) and np.all(np.isfinite(grad))
