"""What the command line changes on a bench goes into that bench's audit trail (issue
34): users added and removed (``supervisor opcua add-user|remove-user``, never the
password), a calibration written into the I/O map (the values, the map's SHA-256 and
diff) — each as ``cli:<login name>``, chained onto whatever the running supervisor
wrote."""

from __future__ import annotations

import csv
import getpass
import hashlib
import io
import json
from pathlib import Path

import pytest
import yaml
from commandrig import io_map as command_map

from supervisor.audit import AUDIT_NAME, AuditLog, read_entries, verify_file
from supervisor.cli.main import main


@pytest.fixture
def io_map(tmp_path: Path) -> Path:
    return command_map(tmp_path)


def entries(tmp: Path) -> list[tuple[str, str, str, dict[str, object]]]:
    path = tmp / "state" / AUDIT_NAME
    assert verify_file(path).ok
    return [(e.actor, e.kind, e.target, e.details_json) for e in read_entries(path)]


def test_a_user_added_then_removed_is_two_entries_without_the_password(
    io_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO("s3cret-pw\n"))
    add = ["opcua", "add-user", "bob", "--role", "operator", "--password-stdin"]
    assert main([*add, "--io-map", str(io_map)]) == 0
    assert main(["opcua", "remove-user", "bob", "--io-map", str(io_map)]) == 0
    users_file = str(tmp_path / "state" / "opcua" / "users.yaml")
    me = f"cli:{getpass.getuser()}"
    assert entries(tmp_path) == [
        (me, "user.add", "bob", {"role": "operator", "new": True, "users_file": users_file}),
        (me, "user.remove", "bob", {"users_file": users_file}),
    ]
    assert b"s3cret" not in (tmp_path / "state" / AUDIT_NAME).read_bytes()


def test_a_calibration_written_into_the_io_map_is_an_entry_with_its_diff(
    io_map: Path, tmp_path: Path
) -> None:
    before = io_map.read_bytes()
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("0,0\n100,98\n200,196\n", encoding="utf-8")
    args = ["calibrate", "current", "--csv", str(pairs), "--io-map", str(io_map), "--board", "1"]
    assert main(args) == 0
    ((actor, kind, target, details),) = entries(tmp_path)
    assert (actor, kind, target) == (
        f"cli:{getpass.getuser()}",
        "calibration.write",
        "chadeche board 1",
    )
    assert isinstance(details, dict)
    assert details["values"] == pytest.approx(
        {"current_slope": 1 / 0.98, "current_offset_ma": 0.0}, abs=1e-9
    )
    assert details["previous_sha256"] == hashlib.sha256(before).hexdigest()
    assert details["sha256"] == hashlib.sha256(io_map.read_bytes()).hexdigest()
    assert "+" in str(details["diff"]) and "current_slope" in str(details["diff"])
    assert details["io_map"] == str(io_map.resolve())
    assert yaml.safe_load(io_map.read_text(encoding="utf-8"))  # still an I/O map


def test_a_csv_export_never_hands_a_spreadsheet_a_formula(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / AUDIT_NAME
    with AuditLog(path) as audit:
        audit.append('hmi:=HYPERLINK("http://x")', "login.failed", "@SUM(1)", {"address": "-"})
    assert main(["audit", "export", "--file", str(path), "--since", "2000-01-01"]) == 0
    row = list(csv.reader(io.StringIO(capsys.readouterr().out)))[1]
    assert row[2:5] == ['hmi:=HYPERLINK("http://x")', "login.failed", "'@SUM(1)"]
    assert (
        main(["audit", "export", "--file", str(path), "--since", "2000-01-01", "--format", "json"])
        == 0
    )
    (entry,) = json.loads(capsys.readouterr().out)["entries"]
    assert entry["target"] == "@SUM(1)"  # JSON: exact
