"""The import-linter contracts of pyproject.toml hold, and break on a wrong import.

The contracts: common imports neither services nor deploy; a service imports neither deploy nor another
service (services.base is their shared helper); the algorithm packages import no bus, recording or
Zenoh code.  The failing cases run lint-imports on a copy of the packages with one bad import added.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")
PACKAGES = ("common", "services", "deploy")
CONTRACTS = [c["name"] for c in
             tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]]


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    if not LINT_IMPORTS.exists():
        pytest.fail(f"{LINT_IMPORTS} not found: install the test extra (pip install -e '.[test]')")
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", "--no-logo", "pyproject.toml"], cwd=cwd,
                          capture_output=True, text=True, timeout=60)


def _contract(words: str) -> str:
    (name,) = [n for n in CONTRACTS if words in n]
    return name


def test_the_layering_contracts_hold():
    assert len(CONTRACTS) == 4
    out = _lint(ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    for name in CONTRACTS:
        assert f"{name} KEPT" in out.stdout, out.stdout


@pytest.mark.parametrize("module, bad_import, broken", [
    ("common/geometry.py", "import deploy.cli", "common imports neither"),
    ("common/camera.py", "from services import evolver", "common imports neither"),
    ("services/planner.py", "import deploy.supervisor", "services do not import deploy"),
    ("services/planner.py", "from services import evolver", "independent of each other"),
    ("services/base.py", "import services.fusion", "independent of each other"),
    ("common/registration/cells.py", "import common.bus", "algorithm packages"),
    ("common/fly/__init__.py", "import zenoh", "algorithm packages"),
    ("common/planning/__init__.py", "from common import recording", "algorithm packages"),
])
def test_a_wrong_import_breaks_its_contract(tmp_path, module, bad_import, broken):
    def only_python(directory, names):
        return [n for n in names if n == "__pycache__" or (Path(directory, n).is_file() and not n.endswith(".py"))]
    for package in PACKAGES:
        shutil.copytree(ROOT / package, tmp_path / package, ignore=only_python)
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / module
    target.write_text(target.read_text() + f"\n{bad_import}  # deliberately wrong\n")

    out = _lint(tmp_path)
    assert out.returncode != 0, out.stdout
    name = _contract(broken)
    assert f"{name} BROKEN" in out.stdout, out.stdout
    assert module[:-3].replace("/", ".").removesuffix(".__init__") in out.stdout, out.stdout
