"""``slamtka plan add/list/show`` and the lookup by Patient ID and laterality."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from slamtka.service.cli import main
from slamtka.service.plans import PlanStore, estimate_landmarks
from slamtka.sim.bone_phantom import build_phantom
from slamtka.solver.plan import Plan

SMITH = Path(__file__).resolve().parents[2] / "shared" / "data" / "knee-smith2019"
SMITH_LANDMARKS = Path(__file__).resolve().parent / "data" / "knee-smith2019-landmarks.json"


@pytest.fixture(scope="module")
def phantom_meshes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("meshes")
    bone = build_phantom("left")
    bone.tibia.export(folder / "tibia.stl")
    bone.fibula.export(folder / "fibula.stl")
    return folder, bone


@pytest.mark.parametrize("side", ["left", "right"])
@pytest.mark.parametrize("with_fibula", [True, False])
def test_landmarks_estimated_from_a_full_length_tibia(side, with_fibula):
    bone = build_phantom(side)
    lm = estimate_landmarks(bone.tibia, bone.fibula if with_fibula else None, side)
    assert np.linalg.norm(lm.knee_centre[:2] - bone.knee_centre[:2]) < 3.0
    axis = lm.T_tibia_anat().R
    mechanical_error = np.degrees(np.arccos(axis[:, 2] @ np.array([0.0, 0.0, 1.0])))
    anterior_error = np.degrees(np.arccos(axis[:, 1] @ bone.anterior))
    assert mechanical_error < (0.5 if with_fibula else 2.0)
    assert anterior_error < 5.0  # the right way round, within a few degrees


def test_plan_add_estimates_landmarks_then_list_show_and_find(phantom_meshes, tmp_path, capsys):
    folder, bone = phantom_meshes
    plans = tmp_path / "plans"
    code = main(["plan", "add", "--plans", str(plans), "--patient-id", "PAT/001 x",
                 "--side", "left", "--tibia", str(folder / "tibia.stl"), "--fibula",
                 str(folder / "fibula.stl"), "--target-ctr", "1", "--target-str", "5",
                 "--tolerance", "2.5", "--segmentation-mm", "0.4"])
    out = capsys.readouterr().out
    assert code == 0 and "estimated from the full-length tibia" in out
    (saved,) = [p for p in plans.iterdir() if not p.name.startswith(".")]
    assert saved.name.startswith("plan-left-") and "PAT" not in saved.name  # no Patient ID in a path
    assert any((saved / "cache").iterdir())  # signed distance fields precomputed
    provenance = json.loads((saved / "provenance.json").read_text())
    assert provenance["landmarks"] == "estimated" and len(provenance["sources"]["tibia"]["sha256"]) == 64

    assert main(["plan", "list", "--plans", str(plans)]) == 0
    listed = capsys.readouterr().out
    assert "PAT/001 x" in listed and "left" in listed and "estimated" in listed
    assert main(["plan", "show", "--plans", str(plans), "--patient-id", "PAT/001 x"]) == 0
    shown = capsys.readouterr().out
    assert "CTR +1.0 deg, STR +5.0 deg, tolerance +-2.5 deg" in shown and "landmarks (estimated)" in shown
    assert "segmentation error 0.40 mm (SD)" in shown

    store = PlanStore(plans)
    plan = store.find("PAT/001 x", "L")
    assert plan.side == "left" and plan.target.str_deg == 5.0 and plan.fibula is not None
    assert plan.segmentation_sd_mm == 0.4
    # A plan file stating an impossible segmentation error is refused by name.
    doc = json.loads((saved / "plan.json").read_text())
    broken = tmp_path / "broken"
    shutil.copytree(saved, broken)
    (broken / "plan.json").write_text(json.dumps({**doc, "segmentation_sd_mm": "big"}))
    with pytest.raises(ValueError, match="segmentation_sd_mm must be a number of mm"):
        Plan.load(broken)
    assert store.find("PAT/001 x", None) is plan  # the only plan; cached while unchanged
    with pytest.raises(ValueError, match="no plan for patient 'PAT/001 x', right side"):
        store.find("PAT/001 x", "R")
    with pytest.raises(ValueError, match="no plan for patient 'OTHER'"):
        store.find("OTHER", None)
    # The same patient and side again is refused unless replaced.
    assert main(["plan", "add", "--plans", str(plans), "--patient-id", "PAT/001 x", "--side", "left",
                 "--tibia", str(folder / "tibia.stl")]) == 2
    assert "use --replace" in capsys.readouterr().err


@pytest.mark.skipif(not (SMITH / "tibia-right.stl").exists(), reason="shared meshes absent")
def test_partial_tibia_needs_landmarks_and_given_landmarks_are_kept(tmp_path, capsys):
    plans = tmp_path / "plans"
    args = ["plan", "add", "--plans", str(plans), "--patient-id", "S2019", "--side", "right",
            "--tibia", str(SMITH / "tibia-right.stl")]
    assert main(args) == 2
    assert "landmarks can only be estimated from a full-length tibia" in capsys.readouterr().err
    assert main(args + ["--landmarks", str(SMITH_LANDMARKS)]) == 0
    assert PlanStore(plans).summaries()[0].landmarks == "given"
    assert main(args + ["--landmarks", str(SMITH_LANDMARKS), "--replace", "--side", "left"]) == 2
    assert "differs from the landmarks' side" in capsys.readouterr().err


def test_bad_meshes_are_refused_with_the_reason(tmp_path, capsys):
    junk = tmp_path / "junk.stl"
    junk.write_text("solid nothing\nendsolid nothing\n")
    assert main(["plan", "add", "--plans", str(tmp_path), "--patient-id", "X", "--side", "right",
                 "--tibia", str(junk)]) == 2
    assert "junk.stl" in capsys.readouterr().err
