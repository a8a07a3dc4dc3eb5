"""A stored plan is loaded for a solve from arrays: no trimesh, nothing rebuilt, and a plan
stored before its arrays were (an older slamtka) still loads and gains them."""

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from slamtka.solver.anatomy import Landmarks
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.plan import Plan
from slamtka.solver.surface import Surface

# Modules a solve must not load: trimesh pulls in scipy.spatial and scipy.special (~1 s),
# libigl (building distance fields) scipy.sparse.
_HEAVY = ("trimesh", "igl", "scipy.sparse", "scipy.spatial", "scipy.special", "scipy.optimize", "rerun",
          "pydicom")


@pytest.fixture(scope="module")
def stored_plan(tmp_path_factory):
    """A small plan (a rod for a tibia), saved and loaded once: its cache filled."""
    rod = trimesh.creation.cylinder(radius=15.0, height=80.0, sections=48)
    landmarks = Landmarks(np.array([0.0, 0.0, 35.0]), np.array([0.0, 0.0, -300.0]),
                          np.array([0.0, 1.0, 0.0]), "right")
    folder = tmp_path_factory.mktemp("plans") / "plan"
    Plan(Surface.of(rod), None, landmarks, build_pin(PinSpec()), PinSpec()).save(folder)
    plan = Plan.load(folder)
    plan.bone_model()
    plan.pin_model()
    return folder, plan


def _copy_files(folder, to):
    """The plan's own files (not its cache) copied into a new folder ``to``."""
    to.mkdir()
    for part in folder.iterdir():
        if part.is_file():
            (to / part.name).write_bytes(part.read_bytes())
    return to


def _cache_listing(folder):
    return {p.name: p.stat().st_mtime_ns for p in (folder / "cache").iterdir()}


def test_a_stored_plan_loads_without_trimesh_and_builds_nothing(stored_plan):
    folder, plan = stored_plan
    before = _cache_listing(folder)
    probe = (f"import sys, json\nfrom slamtka.solver.plan import Plan\n"
             f"plan = Plan.load({str(folder)!r})\nplan.bone_model()\nplan.pin_model()\n"
             "import slamtka.service.solve_case\n"
             f"print(json.dumps(sorted(m for m in sys.modules if m.startswith({_HEAVY!r}))))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []
    assert _cache_listing(folder) == before


def test_a_plan_stored_without_its_arrays_still_loads_and_gains_them(stored_plan, tmp_path):
    folder, plan = stored_plan
    old = _copy_files(folder, tmp_path / "old")
    (old / "cache").mkdir()
    for entry in (folder / "cache").glob("sdf-*.npz"):  # what an older slamtka stored
        (old / "cache" / entry.name).write_bytes(entry.read_bytes())
    again = Plan.load(old)
    for name in ("tibia", "pin_mesh"):
        np.testing.assert_array_equal(getattr(again, name).vertices, getattr(plan, name).vertices)
        np.testing.assert_array_equal(getattr(again, name).faces, getattr(plan, name).faces)
    model = again.bone_model()
    np.testing.assert_array_equal(model.contour.adjacent_edges, plan.bone_model().contour.adjacent_edges)
    assert {p.name.split("-")[0] for p in (old / "cache").iterdir()} == {"sdf", "surface", "silhouettes"}


def test_an_edited_mesh_file_is_read_again(stored_plan, tmp_path):
    """Stored arrays are named by the file's bytes: a replaced mesh never loads stale ones."""
    folder, plan = stored_plan
    copy = _copy_files(folder, tmp_path / "copy")
    wider = trimesh.creation.cylinder(radius=18.0, height=80.0, sections=48)
    wider.export(copy / "tibia.stl")
    assert Plan.load(copy).tibia.extents[0] == pytest.approx(36.0, abs=0.1)
