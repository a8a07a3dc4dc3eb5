"""Shared fixtures: models are expensive (signed distance fields), so build them once."""

from __future__ import annotations

from pathlib import Path

import pytest

from solver.plan import Plan

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "knee-smith2019"
REAL_LANDMARKS = Path(__file__).parent / "data" / "knee-smith2019-landmarks.json"


@pytest.fixture(scope="session")
def phantom_plan() -> Plan:
    plan = Plan.phantom("right")
    plan.bone_model()
    plan.pin_model()
    return plan


@pytest.fixture(scope="session")
def real_plan() -> Plan:
    if not (SHARED_DATA / "tibia-right.stl").exists():
        pytest.skip("the shared real knee meshes are not available")
    plan = Plan.from_meshes(SHARED_DATA / "tibia-right.stl", SHARED_DATA / "fibula-right.stl",
                            REAL_LANDMARKS)
    plan.bone_model()
    plan.pin_model()
    return plan
