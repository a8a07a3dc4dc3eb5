"""Honest failure: spoiled cases are refused with a reason, never measured wrong."""

import json

import numpy as np
import pytest

from slamtka.service.cli import main
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.degenerate import DEGENERATE_KINDS, degenerate_case
from slamtka.solver.plan import Plan


@pytest.fixture(scope="module")
def plans() -> dict[str, Plan]:
    return {side: phantom_plan(side) for side in ("left", "right")}


def test_each_kind_spoils_what_it_says(plans):
    clean = degenerate_case(plans, "outliers", 0).case  # the simulation before it was spoiled
    missing = degenerate_case(plans, "pin-missing", 0)
    assert sum(len(v.contours[label]) == 0 for v in missing.views for label in ("pin1", "pin2")) == 1
    few = degenerate_case(plans, "too-few-points", 0)
    assert max(len(pts) for v in few.views for pts in v.contours.values()) <= 15
    close = degenerate_case(plans, "views-too-close", 0).case.config.view_angles_deg
    assert 0.0 <= close[1] - close[0] <= 10.0
    wrong = degenerate_case(plans, "wrong-side", 0)
    assert wrong.plan.side == "right" and wrong.case.plan.side == "left"
    outliers = degenerate_case(plans, "outliers", 0)
    moved = np.linalg.norm(outliers.views[0].contours["bone"] - clean.views[0].contours["bone"], axis=1)
    assert 0.2 < np.mean(moved > 0) < 0.4


def test_small_degenerate_study_returns_no_wrong_angle(tmp_path):
    out = tmp_path / "degenerate"
    assert main(["bench", "degenerate", "--cases", "1", "--workers", "1", "--out", str(out)]) == 0
    doc = json.loads((out / "degenerate.json").read_text())
    assert [s["kind"] for s in doc["summary"]] == list(DEGENERATE_KINDS)
    assert doc["wrong_angles"] == 0
    for case in doc["cases"]:
        assert case["verdict"] in ("refused", "correct")
        assert case["verdict"] == "correct" or case["reason"]
