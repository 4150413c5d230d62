"""What an integrator's client (node-opcua-client, not asyncua) finds in the bench's address
space (issue 31, findings 7, 9, 10): every channel an instance of one ``ChannelType``
declared once in the types namespace, its state one PackML-style state machine, a type per
device kind, browse names in PascalCase while NodeIds stay the tag names; the bench's
identification (OPC 40001-1 Machinery); a filled Server object; EURange from the
configured ranges and limits, and no made-up range where none is known.

One server for the module (opcuarig, virtual clock), its identification set as an I/O map's
``identification:`` section would; node-opcua only reads (tests/interop/types.js).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import re
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

from supervisor.publish.opcua.settings import Identification, OpcUaSettings

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
INTEROP = Path(__file__).resolve().parent
SCRIPT = INTEROP / "types.js"
TYPES_URI = "urn:bench-supervisor:types"
MACHINERY_URI = "http://opcfoundation.org/UA/Machinery/"
DI_URI = "http://opcfoundation.org/UA/DI/"
PASCAL = re.compile(r"^[A-Z][A-Za-z0-9]*$")
IDENTIFICATION = Identification(
    manufacturer="Battery Lab Ltd",
    model="Chadèche stack, 4 channels",
    serial_number="BL-0042",
    location="Building 3, room 12",
    year_of_construction=2026,
)
ANALOG = ("ch0.manual_current", "ch2.manual_current", "ch0.voltage", "ch0.current", "ch0.power")


def identified(s: OpcUaSettings) -> OpcUaSettings:
    return dataclasses.replace(s, identification=IDENTIFICATION)


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path_factory.mktemp("interop-types"), change=identified) as r:
        yield r


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def seen(rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """What node-opcua saw, read once for the module."""
    tmp = tmp_path_factory.mktemp("node-types")
    cert_der, key = await client_certificate(tmp, "node")
    trust(rig, cert_der)
    cert_pem = pem_of(cert_der, tmp / "node-cert.pem")
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "user": "bob",  # a viewer: browsing and reading need no more
        "password": PASSWORDS["bob"],
        "applicationUri": CLIENT_URI,
        "cert": str(cert_pem),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
        "analog": list(ANALOG),
    }
    proc = await asyncio.create_subprocess_exec(
        node(), str(SCRIPT), json.dumps(cfg), cwd=INTEROP, stdout=asyncio.subprocess.PIPE
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 120)
    result: dict[str, Any] = json.loads(out.decode().splitlines()[-1])
    assert proc.returncode == 0, result.get("error")
    return result


def names(children: list[dict[str, Any]]) -> list[str]:
    return [c["name"] for c in children]


# --- finding 10: types ------------------------------------------------------------------------
async def test_every_channel_is_an_instance_of_one_channel_type_in_the_types_namespace(
    seen: dict[str, Any],
) -> None:
    assert TYPES_URI in seen["namespaces"]
    ch0 = seen["ch0"]
    assert (ch0["type"]["name"], ch0["type"]["uri"]) == ("ChannelType", TYPES_URI)
    assert seen["ch1Type"] == ch0["type"]["nodeId"], "one type for every channel"
    assert seen["channelType"]["supertype"]["name"] == "BaseObjectType"
    bench = seen["bench"]["type"]
    assert (bench["name"], bench["uri"]) == ("BenchType", TYPES_URI)
    # The type declares what every channel has: its measurements, its state machine, its
    # methods, each with a modelling rule (what a client's template instantiates).
    declared = set(names(seen["channelType"]["children"]))
    for member in (
        "Voltage", "Current", "Temperature", "Charge", "Energy", "Mode", "ManualCurrent",
        "StateMachine", "Start", "Hold", "Resume", "Stop", "Abort", "Reset", "SetMode",
        "SetManualCurrent", "AcknowledgeAlarms",
    ):  # fmt: skip
        assert member in declared, member
    rules = seen["channelType"]["rules"]
    assert {rules[m] for m in declared} <= {"Mandatory", "Optional"}
    assert rules["Voltage"] == rules["StateMachine"] == rules["Start"] == "Mandatory"
    # The instance has what its type declares (and its own extra tags besides).
    instance = set(names(ch0["children"]))
    assert {m for m in declared if rules[m] == "Mandatory"} <= instance


async def test_browse_names_are_pascal_case_node_ids_stay_the_tag_names(
    seen: dict[str, Any], rig: Rig
) -> None:
    ns = seen["namespaces"].index(rig.server.namespace)
    for child in seen["ch0"]["children"]:
        assert PASCAL.match(child["name"]), child["name"]
    voltage = next(c for c in seen["ch0"]["children"] if c["name"] == "Voltage")
    assert voltage["nodeId"] == f"ns={ns};s=ch0.voltage"
    diagnostics = {d["name"]: d["nodeId"] for d in seen["diagnostics"]}
    for name in diagnostics:
        assert PASCAL.match(name), name
    assert diagnostics["ScanPeriodS"] == f"ns={ns};s=scan.period_s"
    for device, d in seen["devices"].items():
        for name in d["children"]:
            assert PASCAL.match(name), (device, name)
    assert "EstopOk" in seen["devices"]["adam"]["children"]  # the tag estop.ok


async def test_one_state_variable_per_meaning_the_test_s_state_is_a_state_machine(
    seen: dict[str, Any],
) -> None:
    ch0 = names(seen["ch0"]["children"])
    assert "ChannelState" not in ch0 and "StateName" not in ch0 and "State" not in ch0
    assert "DriveState" in ch0  # the power stage: idle, charging, discharging, faulted
    machine = seen["stateMachine"]
    assert (machine["type"]["name"], machine["type"]["uri"]) == (
        "ChannelStateMachineType",
        TYPES_URI,
    )
    assert machine["supertype"]["name"] == "FiniteStateMachineType"
    assert machine["currentType"]["name"] == "FiniteStateVariableType"
    # An idle channel: the PackML state Idle, number 2 in OPC UA's StateEnumeration, whose
    # Id is the Idle state object of the type.
    assert machine["current"] == {"status": "Good", "value": "Idle"}
    props = machine["currentProperties"]
    assert props["Number"] == {"status": "Good", "value": 2}
    assert machine["currentStateName"]["name"] == "Idle"
    for state in ("Stopped", "Idle", "Execute", "Held", "Aborted", "Complete"):
        assert state in machine["typeStates"]


async def test_each_device_kind_has_its_type_a_subtype_of_device_type(
    seen: dict[str, Any],
) -> None:
    devices = seen["devices"]
    assert devices["chadeche"]["type"]["name"] == "ChadecheDeviceType"
    assert devices["adam"]["type"]["name"] == "Adam5000tcpDeviceType"
    for d in devices.values():
        assert d["type"]["uri"] == TYPES_URI
        assert d["supertype"]["name"] == "BenchDeviceType"
        assert d["children"][:2] == ["Connected", "CommFailures"]


async def test_alarm_objects_are_alarm_condition_instances(seen: dict[str, Any]) -> None:
    assert seen["alarms"], "the bench has alarms"
    assert set(seen["alarms"].values()) == {"ns=0;i=2915"}  # AlarmConditionType
    # The condition's standard variables say its state: room.temp is above its H limit
    # from the start (opcuarig's bench), nobody has acknowledged it.
    room = {k: v["value"] for k, v in seen["conditions"]["room.temp.H"].items()}
    assert (room["EnabledState"], room["EnabledState/Id"]) == ("Enabled", True)
    assert (room["ActiveState"], room["ActiveState/Id"]) == ("Active", True)
    assert (room["AckedState"], room["AckedState/Id"]) == ("Unacknowledged", False)
    assert (room["Retain"], room["ConditionName"]) == (True, "room.temp.H")
    assert room["ConditionClassName"] == "Process"
    for condition in seen["conditions"].values():
        statuses = {k: v["status"] for k, v in condition.items()}
        assert set(statuses.values()) == {"Good"}, statuses


# --- identification (OPC 40001-1) ------------------------------------------------------------
async def test_the_bench_identifies_itself_as_a_machinery_machine(
    seen: dict[str, Any], rig: Rig
) -> None:
    ident = seen["identification"]
    assert ident["uri"] == DI_URI  # the Identification add-in's browse name is DI's
    assert (ident["type"]["name"], ident["type"]["uri"]) == (
        "MachineIdentificationType",
        MACHINERY_URI,
    )
    values = {k: v["value"] for k, v in ident["values"].items()}
    assert values["Manufacturer"] == "Battery Lab Ltd"
    assert values["Model"] == "Chadèche stack, 4 channels"
    assert values["SerialNumber"] == "BL-0042"
    assert values["Location"] == "Building 3, room 12"
    assert values["YearOfConstruction"] == 2026
    assert values["ProductInstanceUri"] == rig.server.namespace
    assert values["SoftwareRevision"] == version()
    # Machinery's entry point: Objects/Machines organizes the bench.
    assert seen["machines"]["uri"] == MACHINERY_URI
    assert seen["benchNodeId"] in seen["machines"]["children"]


def version() -> str:
    from importlib.metadata import version as of

    return of("bench-supervisor")


# --- finding 7: the Server object --------------------------------------------------------------
async def test_build_info_names_the_product_and_its_version(seen: dict[str, Any]) -> None:
    info = {k: v["value"] for k, v in seen["buildInfo"].items()}
    assert info["ProductName"] == "bench-supervisor"
    assert info["SoftwareVersion"] == version()
    assert info["ManufacturerName"]
    assert info["ProductUri"] == "urn:bench-supervisor"
    assert info["BuildNumber"] == version()
    assert isinstance(info["BuildDate"], int | float) and info["BuildDate"] > 0
    assert "FreeOpcUa" not in json.dumps(info)


async def test_server_capabilities_are_filled(seen: dict[str, Any]) -> None:
    caps = seen["capabilities"]
    for name, v in caps.items():
        assert v["status"] == "Good", name
    profiles = caps["ServerProfileArray"]["value"]
    assert profiles  # at least one profile URI
    assert all(p.startswith("http://opcfoundation.org/UA-Profile/") for p in profiles)
    assert caps["LocaleIdArray"]["value"] == ["en"]
    assert caps["MinSupportedSampleRate"]["value"] > 0
    # The service layer's (it pages Browse answers); 0 (none declared) without it.
    assert caps["MaxBrowseContinuationPoints"]["value"] >= 0
    limits = seen["operationLimits"]
    assert limits["MaxNodesPerRead"]["value"] > 0
    assert limits["MaxNodesPerBrowse"]["value"] > 0


async def test_diagnostics_auditing_and_history_capabilities_say_the_truth(
    seen: dict[str, Any],
) -> None:
    # Diagnostics are not collected: EnabledFlag says so (no summary of null values).
    assert seen["diagnosticsEnabled"] == {"status": "Good", "value": False}
    assert seen["auditing"] == {"status": "Good", "value": False}
    history = {k: v["value"] for k, v in seen["historyCapabilities"].items()}
    for name, v in seen["historyCapabilities"].items():
        assert v["status"] == "Good", name
    # This rig's bench keeps no history: nothing served.
    assert history["AccessHistoryDataCapability"] is False
    assert history["InsertDataCapability"] is False
    assert history["DeleteRawCapability"] is False


# --- finding 9: EURange -----------------------------------------------------------------------
async def test_eu_range_comes_from_the_channel_limits(seen: dict[str, Any]) -> None:
    analog = seen["analog"]
    assert analog["ch0.manual_current"]["type"] == "AnalogItemType"
    assert analog["ch0.manual_current"]["range"] == {"low": -0.4, "high": 0.4}
    assert analog["ch2.manual_current"]["range"] == {"low": -0.2, "high": 0.2}
    assert analog["ch0.current"]["range"] == {"low": -0.4, "high": 0.4}
    assert analog["ch0.voltage"]["range"] == pytest.approx({"low": 0.4, "high": 1.9 * 1.2})


async def test_an_analog_tag_without_a_known_range_has_no_made_up_eu_range(
    seen: dict[str, Any],
) -> None:
    power = seen["analog"]["ch0.power"]
    assert power["type"] == "BaseAnalogType"  # Part 8: EURange optional
    assert "EURange" not in power["children"]
    assert "EngineeringUnits" in power["children"]
