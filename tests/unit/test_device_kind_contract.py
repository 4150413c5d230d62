"""Device kinds are independent, whatever their folder is called (issue 29, item 7).

The import-linter contract names no kind: a new folder below ``supervisor/devices/`` is in it
from the start, so a second SCPI supply that imports the EA's codec instead of
:mod:`supervisor.fieldbus.scpi` is refused by ``lint-imports``. Checked on a copy of the
package with one more kind folder, against the project's own contract.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"
CONTRACT_ID = "device-kinds"


def _project_with_kind(tmp_path: Path, kind: str, body: str) -> Path:
    """A copy of the package and its contracts, with one more kind folder."""
    shutil.copytree(
        ROOT / "supervisor", tmp_path / "supervisor", ignore=shutil.ignore_patterns("__pycache__")
    )
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    folder = tmp_path / "supervisor" / "devices" / kind
    folder.mkdir()
    (folder / "__init__.py").write_text(f'"""A second SCPI supply."""\n\n{body}')
    return tmp_path


def _lint_device_kinds(project: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(project)}
    return subprocess.run(
        [str(LINT_IMPORTS), "pyproject.toml", "--contract", CONTRACT_ID, "--no-cache"],
        cwd=project,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.fixture(scope="module")
def lint_imports() -> Path:
    if not LINT_IMPORTS.exists():
        pytest.skip("lint-imports is not installed beside this Python")
    return LINT_IMPORTS


def test_a_new_kind_importing_another_kinds_module_is_refused(
    tmp_path: Path, lint_imports: Path
) -> None:
    project = _project_with_kind(
        tmp_path, "psu2", "from supervisor.devices.ea.protocol import parse_meas_array\n"
    )
    result = _lint_device_kinds(project)
    assert result.returncode != 0, result.stdout
    assert "supervisor.devices.psu2 -> supervisor.devices.ea.protocol" in result.stdout


def test_a_new_kind_may_import_the_shared_protocol_code_and_device_modules(
    tmp_path: Path, lint_imports: Path
) -> None:
    project = _project_with_kind(
        tmp_path,
        "psu2",
        "from supervisor.devices.base import PolledDriver\n"
        "from supervisor.devices.kind import DeviceKind\n"
        "from supervisor.fieldbus.scpi import parse_idn\n"
        "from supervisor.fieldbus.scpi_transport import TcpScpiTransport\n",
    )
    result = _lint_device_kinds(project)
    assert result.returncode == 0, result.stdout + result.stderr


def test_no_module_below_devices_or_fieldbus_imports_itself_in_a_circle() -> None:
    """A circle (the ADAM I/O map model importing its codec inside a function because the
    codec imported the model) makes import order matter and hides which module owns a fact."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("supervisor")
    ours = [m for m in graph.modules if m.startswith(("supervisor.devices", "supervisor.fieldbus"))]
    circles = sorted(
        f"{importer} -> {imported} -> ... -> {importer}"
        for importer in ours
        for imported in graph.find_modules_directly_imported_by(importer)
        if imported in ours and graph.find_shortest_chain(imported, importer) is not None
    )
    assert circles == []
