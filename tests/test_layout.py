"""The package layout the architecture promises: the product (slamtka.service, .solver,
.drivers) imports none of the tooling (slamtka.sim, slamtka.bench), and the command line loads
only the command it runs."""

from __future__ import annotations

import argparse
import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from slamtka.service.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[1]
TOOLING_FOLDERS = (ROOT / "solver" / "sim", ROOT / "service" / "bench")
TOOLING_PACKAGES = ("slamtka.sim", "slamtka.bench")


def _product_modules() -> list[Path]:
    files = [p for folder in ("service", "solver", "drivers") for p in (ROOT / folder).rglob("*.py")]
    return [p for p in files if not any(p.is_relative_to(t) for t in TOOLING_FOLDERS)
            and p.name != "cli.py" or p == ROOT / "service" / "cli.py"]


def _imported_modules(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return names


def test_the_product_imports_none_of_the_tooling():
    offenders = {str(p.relative_to(ROOT)): sorted(m for m in _imported_modules(p)
                                                   if m.startswith(TOOLING_PACKAGES))
                 for p in _product_modules()}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_every_project_import_goes_through_the_one_namespace():
    stray = {str(p.relative_to(ROOT)): sorted(m for m in _imported_modules(p)
                                               if m.split(".")[0] in ("service", "solver", "drivers"))
             for folder in ("service", "solver", "drivers", "tests")
             for p in (ROOT / folder).rglob("*.py")}
    assert {k: v for k, v in stray.items() if v} == {}


def _modules_loaded_by(code: str) -> list[str]:
    probe = (f"import sys, json\n{code}\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
             "('numpy', 'pydicom', 'pynetdicom', 'scipy', 'trimesh', 'cv2', 'rerun')"
             " or m.startswith(('slamtka.sim', 'slamtka.bench')))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_command_list_and_the_health_check_load_nothing_heavy():
    assert _modules_loaded_by("from slamtka.service.cli import build_parser; build_parser()") == []
    assert _modules_loaded_by("from slamtka.service.cli import build_parser; "
                              "build_parser('status')") == []


def test_the_health_check_runs_without_the_solver_or_the_dicom_stack(tmp_path):
    """Parsing is not all: ``slamtka status`` reads the configuration and the status file
    (the C-arm section's drivers, with numpy, are the service's to check at its start)."""
    config = tmp_path / "slamtka.toml"
    config.write_text(f'data_dir = "{tmp_path}"\n[dicom]\nallowed_calling_ae_titles = ["CARM"]\n')
    loaded = _modules_loaded_by("from slamtka.service.cli import main\n"
                                f"assert main(['status', '--config', {str(config)!r}]) == 1")
    assert loaded == []


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_command_registers_itself_under_its_listed_help(name):
    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    listed = {a.dest: a.help for a in sub._choices_actions}
    assert listed[name] == COMMANDS[name].help
    assert len(sub.choices[name]._actions) > 1  # its own options or actions, not a bare name


def test_the_installed_package_works_away_from_the_repository(tmp_path):
    # From a checkout's root the folders `service`, `solver` and `drivers` are importable by
    # accident; a deployed service runs elsewhere, where only `slamtka` exists.
    probe = ("import importlib.util\n"
             "from slamtka.service.results import result_schema\n"
             "assert result_schema()['type'] == 'object'\n"
             "assert [n for n in ('service', 'solver', 'drivers') if importlib.util.find_spec(n)] == []\n")
    done = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
