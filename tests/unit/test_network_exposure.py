"""Issue 27, finding 5: the OPC UA None security policy is offered by default only on
loopback, and ``supervisor check`` warns (exit 0) about every listener off loopback that
serves in clear or without a login."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.cli.main import main
from supervisor.devices.registry import bench_from_data
from supervisor.publish.opcua import OpcUaSettings

ROOT = Path(__file__).resolve().parents[2]


def sim_data(tmp: Path, **sections: dict[str, Any]) -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text("utf-8"))
    data["state_dir"] = str(tmp / "var")
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value}
    return data


def offered(tmp: Path, **opcua: Any) -> tuple[str, ...]:
    return OpcUaSettings.of(bench_from_data(sim_data(tmp, opcua=opcua))).security


def test_the_none_policy_is_offered_by_default_only_on_loopback(tmp_path: Path) -> None:
    everything = ("none", "sign", "sign_and_encrypt")
    assert offered(tmp_path) == everything  # sim.yaml: 127.0.0.1
    assert offered(tmp_path, host="::1") == everything
    assert offered(tmp_path, host="localhost") == everything
    for host in ("0.0.0.0", "192.168.0.5", "bench.lab"):
        assert offered(tmp_path, host=host) == ("sign", "sign_and_encrypt"), host
    # Asked for explicitly, it is offered (and `check` warns: below).
    assert offered(tmp_path, host="0.0.0.0", security=["none"]) == ("none",)


def check(tmp: Path, capsys: pytest.CaptureFixture[str], **sections: dict[str, Any]) -> str:
    path = tmp / "bench.yaml"
    path.write_text(yaml.safe_dump(sim_data(tmp, **sections), sort_keys=False), "utf-8")
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr()
    assert f"{path}: OK" in out.out
    return out.err


def test_check_warns_about_an_opcua_endpoint_off_loopback_with_the_none_policy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = check(tmp_path, capsys, opcua={"host": "0.0.0.0", "security": ["none", "sign"]})
    (line,) = err.splitlines()
    assert "warning: opcua: host '0.0.0.0' is not loopback" in line
    assert "None security policy" in line and "anonymous sessions" in line
    assert "opcua.host: 127.0.0.1" in line
    # No anonymous session: still the None policy, unsigned and in clear.
    err = check(
        tmp_path,
        capsys,
        opcua={"host": "0.0.0.0", "security": ["none"], "anonymous": False},
    )
    assert "None security policy" in err and "anonymous" not in err
    # The default off loopback (no None) and anything on loopback: nothing to say.
    assert check(tmp_path, capsys, opcua={"host": "0.0.0.0"}) == ""
    assert check(tmp_path, capsys, opcua={"security": ["none"]}) == ""


def test_check_warns_about_an_http_listener_off_loopback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = check(tmp_path, capsys, hmi={"host": "0.0.0.0", "login": True})
    (line,) = err.splitlines()
    assert "warning: hmi: host '0.0.0.0' is not loopback" in line
    assert "plain HTTP" in line and "hmi.anonymous_read: false" in line
    err = check(tmp_path, capsys, hmi={"host": "0.0.0.0", "login": True, "anonymous_read": False})
    assert "plain HTTP" in err and "anonymous_read" not in err
    # Without login off loopback it is an error, as before (exit 2).
    path = tmp_path / "open.yaml"
    data = sim_data(tmp_path, hmi={"host": "0.0.0.0", "login": False})
    path.write_text(yaml.safe_dump(data, sort_keys=False), "utf-8")
    assert main(["check", str(path)]) == 2
