"""Shared fixtures (models are expensive: signed distance fields, so built once) and the two
tiers: `make test` runs the fast one; the modules below, which run the real service end to
end or a study in small, and tests marked ``system`` form the second (`make test-system`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamtka.sim.bone_phantom import phantom_plan as build_phantom_plan
from slamtka.sim.simulate import SimulationConfig, default_camera, simulate_case
from slamtka.sim.xray import XRayParams, XRayScene, render_radiograph
from slamtka.solver.plan import Plan

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "knee-smith2019"
REAL_LANDMARKS = Path(__file__).parent / "data" / "knee-smith2019-landmarks.json"


@pytest.fixture(scope="session")
def phantom_plan() -> Plan:
    plan = build_phantom_plan("right")
    plan.bone_model()
    plan.pin_model()
    return plan


@pytest.fixture(scope="session")
def scene(phantom_plan):
    return XRayScene.from_plan(phantom_plan)


@pytest.fixture(scope="session")
def radiographs(phantom_plan, scene):
    """The phantom case of seed 2 and its idealised radiographs, one per view."""
    case = simulate_case(phantom_plan, SimulationConfig(seed=2))
    return case, [render_radiograph(phantom_plan, T, case.truth_T_tibia_pin, default_camera(), XRayParams(),
                                    np.random.default_rng(k), scene)
                  for k, T in enumerate(case.truth_T_cam_tibia)]


@pytest.fixture(scope="session")
def real_plan() -> Plan:
    if not (SHARED_DATA / "tibia-right.stl").exists():
        pytest.skip("the shared real knee meshes are not available")
    plan = Plan.from_meshes(SHARED_DATA / "tibia-right.stl", SHARED_DATA / "fibula-right.stl",
                            REAL_LANDMARKS)
    plan.bone_model()
    plan.pin_model()
    return plan


SYSTEM_MODULES = frozenset({
    "test_calibration", "test_cli", "test_degenerate", "test_imaging_chain", "test_imaging_realism",
    "test_link_sim", "test_measure", "test_service_bench_network", "test_service_e2e",
    "test_service_faults", "test_service_hardening", "test_service_loop", "test_service_plans",
    "test_service_workflow_e2e",
})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.stem in SYSTEM_MODULES:
            item.add_marker(pytest.mark.system)

