"""schemathesis against a real ``supervisor run`` (issue 27): the simulated bench of
io_maps/sim.yaml (a temporary copy on free loopback ports, login on), an operator's
session, and every phase of ``st run`` (examples, coverage, fuzzing, stateful with the
links it infers) with a bounded number of examples per operation: no 5xx, every status,
content type, header and body as supervisor/hmi/openapi.yaml describes, invalid data
refused, undeclared methods answered 405.

Left out of the run: ``POST /api/logout`` (it would end the session the run uses),
``GET /api/ws`` (a WebSocket, tests/integration/test_hmi_live.py), ``GET /api/sim/state``
(``supervisor sim``'s control API only: ``supervisor run`` has no such route) and
``POST /api/recipes/dryrun`` (a valid recipe's preview runs for up to
``DRY_RUN_PREVIEW_TIMEOUT_S``: tests/integration/test_hmi_recipes_api.py). Checks left
out: ``positive_data_acceptance`` (a valid command is refused in many states: 409 is an
answer, not a failure), ``ignored_auth`` (``hmi.anonymous_read`` answers reads without a
session, as designed) and ``allow_header_conformance`` (``/api/recipes/validate`` is also
``/api/recipes/{name}`` named "validate": its 405's ``Allow`` rightly lists GET and PUT).

Prints the number of operations and of test cases run, and the failures (0)."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "browser"))
from browserrig import Supervisor, supervisor_fixture

pytestmark = pytest.mark.integration

MAX_EXAMPLES = 10
"""Test cases per operation and phase (the whole run takes about 20 s on the bench's PC)."""
SEED = 27
EXCLUDED_PATHS = ("/api/logout", "/api/ws", "/api/sim/state", "/api/recipes/dryrun")
EXCLUDED_CHECKS = ("positive_data_acceptance", "ignored_auth", "allow_header_conformance")
ST = Path(sys.executable).parent / "st"
UPLOT = Path(__file__).resolve().parents[2] / "hmi" / "node_modules" / "uplot" / "dist"


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Supervisor]:
    yield from supervisor_fixture(tmp_path_factory.mktemp("schemathesis-bench"))


def session_cookie(bench: Supervisor, user: str) -> str:
    opener = bench.opener(user)  # logged in
    for handler in opener.handlers:
        if isinstance(handler, urllib.request.HTTPCookieProcessor):
            for cookie in handler.cookiejar:
                if cookie.name == "bench_session" and cookie.value:
                    return cookie.value
    raise AssertionError(f"{user}: no session cookie after the login")


def run_schemathesis(
    bench: Supervisor, report: Path, token: str
) -> subprocess.CompletedProcess[str]:
    command = [
        str(ST),
        "run",
        f"{bench.base}/api/openapi.json",
        "--header",
        f"Cookie: bench_session={token}",
        "--checks",
        "all",
        "--exclude-checks",
        ",".join(EXCLUDED_CHECKS),
        *[arg for path in EXCLUDED_PATHS for arg in ("--exclude-path", path)],
        "--max-examples",
        str(MAX_EXAMPLES),
        "--seed",
        str(SEED),
        "--workers",
        "1",
        "--request-timeout",
        "20",
        "--report",
        "json",
        "--report-json-path",
        str(report),
    ]
    # Run in the report's folder: schemathesis keeps a cache (.schemathesis/) where it runs.
    return subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=170,
        check=False,
        cwd=report.parent,
    )


def test_schemathesis_finds_no_5xx_and_every_answer_as_described(
    bench: Supervisor, tmp_path: Path
) -> None:
    if not ST.exists():
        pytest.fail(f"{ST} is missing: pip install -e '.[dev]' installs schemathesis")
    if not UPLOT.exists():  # the screens' files answer 503 "run make hmi" without it
        pytest.fail(f"{UPLOT} is missing: `make hmi` installs it (npm ci)")
    report = tmp_path / "schemathesis.json"
    done = run_schemathesis(bench, report, session_cookie(bench, "operator"))
    assert report.exists(), f"schemathesis wrote no report:\n{done.stdout}\n{done.stderr}"
    result: dict[str, Any] = json.loads(report.read_text(encoding="utf-8"))
    operations, cases = result["operations"], result["test_cases"]
    failures = cases["unique_failures"]
    phases = ", ".join(f"{name} {p['status']}" for name, p in result["phases"].items())
    print(
        f"schemathesis {result['schemathesis_version']}: {operations['tested']} operations"
        f" ({operations['total']} described), {cases['generated']} test cases,"
        f" {failures} failures, {len(result['errors'])} errors; phases: {phases}"
    )
    assert (failures, len(result["errors"])) == (0, 0), done.stdout[-20000:]
    assert done.returncode == 0, done.stdout[-5000:]
    assert operations["tested"] == operations["total"] - len(EXCLUDED_PATHS)
    assert all(p["status"] == "success" for p in result["phases"].values()), result["phases"]
    # The bench went through it: still scanning, its devices connected.
    assert bench.tag("adam.connected") is True and bench.tag("ea.connected") is True
