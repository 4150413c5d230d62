"""``supervisor opcua selftest URL`` against ``supervisor run`` (issue 31): every check an
integrator's client makes passes, from another process, logged in as an operator (the
method and condition checks need a user); an anonymous run skips those two and says why;
a URL that is not one is exit 2 with one line."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from test_opcua_run import opcua_map, supervisor

from supervisor.cli.selftest import CHECKS

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def served(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[tuple[str, Path]]:
    tmp = tmp_path_factory.mktemp("selftest")
    io_map, port = opcua_map(tmp)
    added = supervisor(
        "opcua", "add-user", "alice", "--role", "operator", "--io-map", str(io_map),
        "--password-stdin", cwd=tmp, stdin="s3cret\n",
    )  # fmt: skip
    assert added.returncode == 0, added.stderr
    proc = subprocess.Popen(  # noqa: ASYNC220 - Popen only starts it; reads go to threads
        [sys.executable, "-m", "supervisor.cli.main", "run", str(io_map), "--http-port", "0"],
        cwd=tmp,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        assert proc.stdout is not None
        banner: list[str] = []
        while not banner or not banner[-1].startswith("Ctrl-C"):
            line = await asyncio.to_thread(proc.stdout.readline)
            assert line, f"supervisor exited: {banner}"
            banner.append(line)
        yield f"opc.tcp://127.0.0.1:{port}/supervisor", tmp
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            await asyncio.to_thread(proc.wait, 30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def _selftest(url: str, cwd: Path, *args: str, stdin: str | None = None) -> tuple[int, list[str]]:
    done = supervisor("opcua", "selftest", url, *args, cwd=cwd, stdin=stdin)
    # One line a check on stdout; nothing else (asyncua's own log of the faults the checks
    # provoke on purpose is not the integrator's to read).
    assert done.stderr == "", done.stderr
    return done.returncode, done.stdout.splitlines()


async def test_every_check_passes_for_an_operator(served: tuple[str, Path]) -> None:
    url, cwd = served
    code, lines = await asyncio.to_thread(
        _selftest, url, cwd, "--user", "alice", "--password-stdin", stdin="s3cret\n"
    )
    verdicts = {line.split()[1].rstrip(":"): line.split()[0] for line in lines[:-1]}
    assert set(verdicts) == {name for name, _ in CHECKS}, lines
    assert [line for line in lines if not line.startswith("PASS")] == [
        f"{len(CHECKS)} passed, 0 failed, 0 skipped"
    ], "\n".join(lines)
    assert code == 0


async def test_an_anonymous_run_skips_the_calls_and_says_why(served: tuple[str, Path]) -> None:
    url, cwd = served
    code, lines = await asyncio.to_thread(_selftest, url, cwd)
    skipped = [line for line in lines if line.startswith("SKIP")]
    assert [line.split()[1].rstrip(":") for line in skipped] == [
        "methods.wrong-object",
        "conditions.acknowledge-unknown-event",
    ]
    assert all("give --user" in line for line in skipped)
    assert code == (1 if any(line.startswith("FAIL") for line in lines) else 0)


async def test_a_url_that_is_not_one_is_exit_2_with_one_line(tmp_path: Path) -> None:
    done = await asyncio.to_thread(supervisor, "opcua", "selftest", "localhost:4840", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "supervisor opcua selftest: give the server's URL (opc.tcp://HOST:PORT),"
        " not 'localhost:4840'"
    ]
