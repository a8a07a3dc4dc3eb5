"""Bad plan inputs (meshes, landmarks, targets, plan folders, cached fields) are refused with
the file and the problem named, and never stop the valid ones from being used."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh

from slamtka.service.cli import main
from slamtka.service.plans import PlanStore, _folder_name, estimate_landmarks
from slamtka.solver.anatomy import Landmarks
from slamtka.solver.meshes import MeshError, load_mesh
from slamtka.solver.plan import BONE_EXTENT_MM, Plan, Target
from slamtka.solver.sdf import SignedDistanceField
from slamtka.solver.surface import Surface

KNEE, ANKLE = [0.0, 0.0, 180.0], [0.0, 0.0, -180.0]


def _write_landmarks(path, knee=KNEE, anterior=(0.0, 1.0, 0.0)):
    path.write_text(json.dumps({"units": "mm", "knee_centre": list(knee), "ankle_centre": ANKLE,
                                "anterior": list(anterior), "side": "right"}))
    return path


@pytest.fixture
def bones(tmp_path):
    """A box 'tibia' around the landmarks' axis and a box 'fibula' beside it, as STL files."""
    tibia = tmp_path / "tibia.stl"
    trimesh.creation.box(extents=(60, 60, 380)).export(tibia)
    fibula = tmp_path / "fibula.stl"
    trimesh.creation.box(extents=(15, 15, 340),
                         transform=trimesh.transformations.translation_matrix([40, 0, 0])).export(fibula)
    return tibia, fibula, _write_landmarks(tmp_path / "landmarks.json")


# 1. meshes with holes load (no networkx); garbage is "not a readable mesh"
def test_a_mesh_with_a_hole_loads_with_a_warning(tmp_path, caplog):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    sphere.update_faces(np.arange(len(sphere.faces)) != 7)
    sphere.export(tmp_path / "open.stl")
    with caplog.at_level(logging.WARNING):
        mesh = load_mesh(tmp_path / "open.stl", BONE_EXTENT_MM, units="mm")
    assert len(mesh.faces) == len(sphere.faces) and not mesh.is_watertight
    assert "open.stl: mesh is not watertight (1 pieces)" in caplog.text
    with pytest.raises(MeshError, match="open.stl: mesh is not watertight"):
        load_mesh(tmp_path / "open.stl", BONE_EXTENT_MM, units="mm", require_watertight=True)


def test_random_bytes_are_not_a_readable_mesh(tmp_path):
    junk = tmp_path / "junk.stl"
    junk.write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(MeshError, match="junk.stl: not a readable mesh"):
        load_mesh(junk, BONE_EXTENT_MM)


# 2. the distance field's size is capped; a fibula must lie beside the tibia
def test_distance_field_grid_is_capped_before_anything_is_sampled():
    near, far = trimesh.creation.box(extents=(100, 100, 100)), trimesh.creation.box(extents=(100, 100, 100))
    far.apply_translation([3000.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"span 3116 x 116 x 116 mm.*voxels \(at most"):
        SignedDistanceField.build([near, far], 1.0, 8.0)


def test_a_model_small_enough_for_its_band_to_cover_the_grid_has_a_field():
    field = SignedDistanceField.build([trimesh.creation.box(extents=(2, 2, 2))], 1.0, 1.0)
    assert field.values.shape == (5, 5, 5)
    assert np.isclose(field.query(np.zeros((1, 3)))[0][0], -1.0, atol=1e-6)


def test_a_fibula_far_from_the_tibia_is_refused(bones):
    tibia, fibula, landmarks = bones
    Plan.from_meshes(tibia, fibula, landmarks)  # beside it: accepted
    far = trimesh.load(fibula)
    far.apply_translation([3000.0, 0.0, 0.0])
    far.export(fibula)
    with pytest.raises(ValueError, match=r"fibula.stl: the fibula lies 3002 mm away from the tibia"):
        Plan.from_meshes(tibia, fibula, landmarks)


# 3. one unreadable plan folder never blocks the others; staging folders are not plans
def _plan_doc(folder, patient_id, side="right"):
    folder.mkdir(parents=True)
    (folder / "plan.json").write_text(json.dumps({"patient_id": patient_id, "side": side,
                                                  "target": {"ctr_deg": 0.0}}))


def test_unreadable_plan_folders_are_reported_and_skipped(tmp_path, monkeypatch, caplog, capsys):
    monkeypatch.setattr(PlanStore, "load", lambda self, folder: folder)  # no models needed
    _plan_doc(tmp_path / ".staging-0123", "STAGED")
    _plan_doc(tmp_path / _folder_name("P1", "right"), "P1")
    truncated = tmp_path / "zzz" / "plan.json"
    truncated.parent.mkdir()
    truncated.write_text('{"patient_id": "Q", "si')
    listed = tmp_path / _folder_name("BAD", "right") / "plan.json"
    listed.parent.mkdir()
    listed.write_text("[1, 2, 3]")
    store = PlanStore(tmp_path)
    with caplog.at_level(logging.WARNING):
        assert store.find("P1", "R") == tmp_path / _folder_name("P1", "right")
    assert "zzz is unreadable" in caplog.text and "must hold a JSON object" in caplog.text
    with pytest.raises(ValueError, match="no plan for patient 'STAGED'"):
        store.find("STAGED", None)
    for laterality in ("R", None):
        with pytest.raises(ValueError, match=rf"'BAD' is unreadable: {listed}: must hold a JSON object, not list"):
            store.find("BAD", laterality)
    assert main(["plan", "list", "--plans", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "P1" in out and "STAGED" not in out
    assert f"unreadable: {truncated}: not valid JSON" in out


# 4. landmarks: a zero anterior direction and non-finite points are refused by file
@pytest.mark.parametrize("field, value, message", [
    ("anterior", [0, 0, 0], "anterior direction is a zero vector"),
    ("knee_centre", [float("nan"), 0, 0], "knee_centre must be three finite numbers"),
    ("anterior", [float("inf"), 0, 0], "anterior must be three finite numbers"),
])
def test_degenerate_landmarks_are_refused(tmp_path, field, value, message):
    path = _write_landmarks(tmp_path / "lm.json")
    doc = json.loads(path.read_text())
    doc[field] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"lm.json: .*{message}"):
        Landmarks.load(path)


# 5. planned angles and tolerance must be finite numbers
@pytest.mark.parametrize("kwargs", [{"ctr_deg": float("nan")}, {"str_deg": float("inf")},
                                    {"tolerance_deg": float("nan")}, {"ctr_deg": "5"}])
def test_non_finite_targets_are_refused(kwargs):
    (name,) = kwargs
    with pytest.raises(ValueError, match=f"target {name} must be a finite number of degrees"):
        Target(**kwargs)
    assert Target(ctr_deg=np.float64(1.0), str_deg=np.int64(2)).str_deg == 2  # numbers still do


# 6. estimating landmarks on something that is not a tibia
def test_landmarks_of_a_cube_cannot_be_estimated(tmp_path, capsys):
    with pytest.raises(ValueError, match="does not look like a tibia"):
        estimate_landmarks(trimesh.creation.box(extents=(300, 300, 300)), None, "right")
    cube = tmp_path / "cube.stl"
    trimesh.creation.box(extents=(300, 300, 300)).export(cube)
    assert main(["plan", "add", "--plans", str(tmp_path / "plans"), "--patient-id", "X",
                 "--side", "right", "--tibia", str(cube)]) == 2
    assert "cube.stl: the mesh has no surface where the tibial plateau" in capsys.readouterr().err


# 7. landmarks far from the tibia mesh
def test_landmarks_far_from_the_tibia_are_refused(bones, tmp_path, capsys):
    tibia, _, _ = bones
    far = _write_landmarks(tmp_path / "far.json", knee=[0.0, 0.0, 1700.0])
    far_doc = json.loads(far.read_text())
    far_doc["ankle_centre"] = [0.0, 0.0, 1340.0]
    far.write_text(json.dumps(far_doc))
    with pytest.raises(ValueError, match=r"far.json: the knee centre .* lies 1510 mm outside"):
        Plan.from_meshes(tibia, None, far)
    plans = tmp_path / "plans"
    assert main(["plan", "add", "--plans", str(plans), "--patient-id", "X", "--side", "right",
                 "--tibia", str(tibia), "--landmarks", str(far)]) == 2
    assert "far.json: the knee centre" in capsys.readouterr().err
    assert not plans.exists() or not any(plans.iterdir())


# 8. a damaged cached distance field is rebuilt
@pytest.mark.parametrize("damage", [lambda b: b[: len(b) // 2], lambda b: b""])
def test_an_unreadable_cached_field_is_rebuilt(tmp_path, caplog, damage):
    meshes = [Surface.of(trimesh.creation.icosphere(subdivisions=1, radius=5.0))]
    fresh = SignedDistanceField.cached(meshes, 2.0, 20.0, tmp_path)
    (path,) = tmp_path.glob("sdf-*.npz")
    path.write_bytes(damage(path.read_bytes()))
    with caplog.at_level(logging.WARNING):
        rebuilt = SignedDistanceField.cached(meshes, 2.0, 20.0, tmp_path)
    assert "unreadable cached distance field" in caplog.text and path.name in caplog.text
    np.testing.assert_array_equal(rebuilt.values, fresh.values)
    np.testing.assert_array_equal(SignedDistanceField.load(path).values, fresh.values)


@pytest.mark.parametrize("patient_id", ["", "   ", "A\\B", "line\nbreak", "x" * 65])
def test_a_plan_needs_a_patient_id_images_can_carry(tmp_path, capsys, patient_id):
    with pytest.raises(SystemExit) as stop:
        main(["plan", "add", "--plans", str(tmp_path), "--patient-id", patient_id,
              "--side", "right", "--tibia", str(tmp_path / "tibia.stl")])
    assert stop.value.code == 2
    assert "is not a DICOM Patient ID" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
