"""A fast command line (issue 30): every command imports only what it needs.

``supervisor check recipes/nimh-ds2710.yaml`` took 1.2–1.5 s, about 0.9 s of it importing
the OPC UA server, the Modbus server and its HTTP simulator, aiohttp, python-can… before
the file was read. The commands that serve nothing (check, schema, dry-run, --help) must
not import the packages of a server, a field bus or a database client. Each command runs
in a process of its own, so ``sys.modules`` holds what that command imported and nothing
a test before it did. (The wall time is a figure, ``supervisor bench cli``, not asserted.)
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SERVER_PACKAGES = (
    "asyncua",  # the OPC UA server and client
    "cryptography",  # OPC UA certificates
    "aiohttp",  # the HTTP API and screens; pymodbus's simulator's web page
    "pymodbus",  # the Modbus TCP client and server (ADAM-5000)
    "can",  # python-can (the BMS over socketcand)
    "cantools",  # the BMS's DBC file
    "influxdb_client",
    "paho",  # paho-mqtt (the Sparkplug B edge node)
    "google",  # protobuf (Sparkplug B payloads)
    "hypothesis",  # a test library: never at run time
)
"""Top-level packages no command that serves nothing may import."""

# Runs the command line's ``main`` in a fresh interpreter, then prints what it imported.
SCRIPT = """
import json, sys
from supervisor.cli.main import main
code = main(sys.argv[1:])
sys.stdout.flush()
print("\\nIMPORTED " + json.dumps(sorted(sys.modules)))
sys.exit(code)
"""


def imported_by(*argv: str) -> tuple[int, str, set[str]]:
    """Exit code, output and the modules imported by ``supervisor ARGV...``."""
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, *argv],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        check=False,
    )
    out, _, imported = done.stdout.rpartition("\nIMPORTED ")
    assert imported, f"no import list: stdout {done.stdout!r}, stderr {done.stderr!r}"
    return done.returncode, out + done.stderr, set(json.loads(imported))


def packages(modules: set[str]) -> set[str]:
    """The top-level packages of these modules that no command serving nothing may import."""
    return {m.split(".")[0] for m in modules} & set(SERVER_PACKAGES)


COMMANDS = {
    "check a recipe": (["check", "recipes/nimh-ds2710.yaml"], "recipes/nimh-ds2710.yaml: OK"),
    "check an I/O map": (["check", "io_maps/sim.yaml"], "io_maps/sim.yaml: OK"),
    "check every kind's map": (
        ["check", "io_maps/bench-adam-ea.yaml", "io_maps/load16.yaml"],
        "io_maps/load16.yaml: OK",
    ),
    "help": (["--help"], "usage: supervisor"),
    "modbus map": (["modbus", "map", "io_maps/sim.yaml"], "104,300105,04,float32,big,ch0.voltage"),
    "check's help": (["check", "--help"], "usage: supervisor check"),
    "dry-run": (
        ["dry-run", "recipes/nimh-ds2710.yaml", "--max-hours", "0.1"],
        "did not finish within 0.1 h",
    ),
}


@pytest.mark.parametrize("name", COMMANDS)
def test_a_command_that_serves_nothing_imports_no_server_bus_or_database_package(
    name: str,
) -> None:
    argv, said = COMMANDS[name]
    code, out, imported = imported_by(*argv)
    assert said in out
    assert code in (0, 1), out  # dry-run stopped by --max-hours: 1
    assert sorted(packages(imported)) == []


def test_schema_imports_no_server_bus_or_database_package(tmp_path: Path) -> None:
    code, out, imported = imported_by("schema", "--out", str(tmp_path))
    assert code == 0, out
    assert (tmp_path / "io_maps" / "bench.schema.json").is_file()
    assert sorted(packages(imported)) == []


def test_a_usage_error_is_still_exit_2_and_one_line() -> None:
    code, out, imported = imported_by("check")
    assert code == 2
    assert "supervisor check: the following arguments are required: files" in out
    assert sorted(packages(imported)) == []


def test_a_recipe_check_does_not_build_the_io_map_model() -> None:
    """A recipe names no device: the device kinds and their I/O map model (pydantic models
    of every kind, the larger part of what remains) are not imported to check one."""
    code, out, imported = imported_by("check", "recipes/nimh-ds2710.yaml")
    assert code == 0, out
    assert (
        sorted(
            m for m in imported if m.startswith(("supervisor.devices", "supervisor.config.models"))
        )
        == []
    )


def test_pymodbus_comes_with_a_modbus_master_made_at_wiring_not_with_the_codes() -> None:
    """The codes (an I/O map's check) import no pymodbus; a master imports it when the bench
    is wired, so that its first connect, on the running loop, does not (tens of ms)."""
    script = (
        "import sys\n"
        "from supervisor.fieldbus import modbus\n"
        "print('pymodbus' in sys.modules)\n"
        "modbus.ModbusTcpMaster('adam1', '127.0.0.1', 502)\n"
        "print(all(m in sys.modules for m in ('pymodbus.client', 'pymodbus.exceptions')))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        check=True,
    )
    assert done.stdout.split() == ["False", "True"]


def test_the_opc_ua_users_file_is_kept_without_the_opc_ua_stack(tmp_path: Path) -> None:
    """``supervisor opcua list-users`` reads a users file: no asyncua, no cryptography (the
    server's settings live apart from the server, ``publish/opcua/settings.py``)."""
    io_map = tmp_path / "bench.yaml"
    text = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    io_map.write_text(text.replace("state_dir: var/sim", f"state_dir: {tmp_path}"), "utf-8")
    code, out, imported = imported_by("opcua", "list-users", "--io-map", str(io_map))
    assert code == 0, out
    assert sorted(packages(imported)) == []
