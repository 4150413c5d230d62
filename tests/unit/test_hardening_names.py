"""Issue 28, findings 7, 8 and 9: what the CLI, a profile's ``repeat`` and a load profile
CSV are handed, refused with one clear message (exit 2, no traceback), never misread."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.chains.profile_csv import read_profile_csv
from supervisor.config.limits import MAX_PROFILE_REPEAT
from supervisor.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    """The real ``supervisor`` command in a child process."""
    return subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", *args],
        capture_output=True,
        text=True,
        check=False,
        cwd=cwd,
        timeout=120,
    )


def refused(proc: subprocess.CompletedProcess[str], *words: str) -> str:
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, proc.stderr
    for word in words:
        assert word in proc.stderr
    return proc.stderr


# --- finding 8: profile repeat ------------------------------------------------------------


def test_a_profile_repeated_10_to_the_400_times_is_refused_at_load_at_its_value(
    tmp_path: Path,
) -> None:
    path = tmp_path / "repeat.yaml"
    path.write_text(
        "recipe: rep\nsteps:\n  - id: p\n    profile:\n"
        "      rows: [{t: 0, current: 0.1}, {t: 10, current: 0}]\n"
        f"      repeat: {10**400}\n",
        encoding="utf-8",
    )
    err = refused(cli("check", str(path)), f"{path}:6:15:", "too many")
    assert f"at most {MAX_PROFILE_REPEAT:,} times (README: Input limits)" in err
