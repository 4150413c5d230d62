"""The bench's address space as an OPC UA client sees it over loopback: the tree (PascalCase
browse names), NodeIds equal to tag names, analog tags with their units and range, quality
as status codes, timestamps, the PackML state machine, and subscriptions that follow the
scan.

One server for the module (it takes seconds to start); the tests only read, or put back
what they change.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from datetime import UTC, datetime

import pytest
import pytest_asyncio
from asyncua import ua
from opcuarig import Collector, Rig, eventually, opcua_rig

from supervisor.devices.chadeche.sim import SimulatedBoards

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
VT = ua.VariantType


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path_factory.mktemp("opcua-space")) as r:
        yield r


async def names(node: object) -> list[str]:
    return [(await n.read_browse_name()).Name for n in await node.get_children()]  # type: ignore[attr-defined]


async def test_the_tree_mirrors_the_bench_channels_devices_alarms_diagnostics(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        bench = c.get_node(ua.NodeId("/Bench", ns))
        objects = await names(c.nodes.objects)
        assert "Bench" in objects
        assert await names(bench) == [
            "Channels", "Devices", "Alarms", "Diagnostics", "ForceTag", "UnforceTag",
            "EmergencyStop", "ResetEmergencyStop",
            "Identification",
        ]  # fmt: skip
        channels = c.get_node(ua.NodeId("/Bench/Channels", ns))
        assert await names(channels) == ["ch0", "ch1", "ch2", "ch3"]
        ch0 = await names(c.get_node(ua.NodeId("/Bench/Channels/ch0", ns)))
        for friendly in (
            "Voltage", "Current", "Temperature", "Charge", "Energy", "StateMachine", "Mode",
            "Recipe", "Step", "StepName", "StepTime", "Cycle", "Progress", "ETA", "DriveState",
        ):  # fmt: skip
            assert friendly in ch0, friendly
        for method in (
            "Start", "Hold", "Resume", "Advance", "Stop", "Abort", "Reset", "SetMode",
            "SetManualCurrent", "AcknowledgeAlarms",
        ):  # fmt: skip
            assert method in ch0, method
        assert len(ch0) == len(set(ch0)), "browse names are unique in a channel"
        devices = c.get_node(ua.NodeId("/Bench/Devices", ns))
        assert sorted(await names(devices)) == ["adam", "chadeche"]
        adam = await names(c.get_node(ua.NodeId("/Bench/Devices/adam", ns)))
        assert adam[:2] == ["Connected", "CommFailures"]
        assert {"EstopOk", "RoomTemp", "PackVoltage"} <= set(adam)  # its raw points
        alarms = await names(c.get_node(ua.NodeId("/Bench/Alarms", ns)))
        assert set(alarms) == {a.id for a in rig.bench.alarms or []}
        diagnostics = await names(c.get_node(ua.NodeId("/Bench/Diagnostics", ns)))
        for name in ("ScanDurationS", "ScanJitterS", "ScanOverruns", "OpcuaDropped"):
            assert name in diagnostics
        assert {"OpcuaQueueDepth", "OpcuaClients"} <= set(diagnostics)


async def test_a_node_id_is_the_tag_name_and_reads_the_tag_value(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        for tag in ("ch0.voltage", "ch1.mode", "adam.connected", "ch2.chain.cycle"):
            node = c.get_node(f"ns={ns};s={tag}")
            assert await node.read_value() == rig.bench.db[tag].value
        voltage = c.get_node(ua.NodeId("ch0.voltage", ns))
        assert (await voltage.read_browse_name()).Name == "Voltage"
        assert (await voltage.read_description()).Text == "Cell voltage"


async def test_an_analog_tag_is_an_analog_item_with_its_unit_and_range(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        voltage = c.get_node(ua.NodeId("ch0.voltage", ns))
        assert await voltage.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogItemType)
        assert await voltage.read_data_type() == ua.NodeId(ua.ObjectIds.Double)
        eu_range = await (await voltage.get_child("0:EURange")).read_value()
        assert (eu_range.Low, eu_range.High) == pytest.approx(
            rig.bench.db["ch0.voltage"].spec.range
        )
        eu_node = await voltage.get_child("0:EngineeringUnits")
        assert eu_node.nodeid.NamespaceIndex == ns  # a property id in namespace 0 breaks clients
        eu = await eu_node.read_value()
        assert eu.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
        assert (eu.UnitId, eu.DisplayName.Text) == (5655636, "V")  # UNECE VLT
        units = {  # UNECE AMP, AMH, WHR, WTT, SEC, CEL
            "ch0.current": 4279632,
            "ch0.charge_ah": 4279624,
            "ch0.energy_wh": 5720146,
            "ch0.power": 5723220,
            "ch0.chain.step_time": 5457219,
            "room.temp": 4408652,
        }
        for tag, unit_id in units.items():
            node = c.get_node(ua.NodeId(tag, ns))
            assert (
                await (await node.get_child("0:EngineeringUnits")).read_value()
            ).UnitId == unit_id
        # A tag without a configured range is a BaseAnalogType with its unit and no EURange
        # (issue 31, finding 9: not every finite Double).
        power = c.get_node(ua.NodeId("ch0.power", ns))
        assert await power.read_type_definition() == ua.NodeId(ua.ObjectIds.BaseAnalogType)
        assert [(await n.read_browse_name()).Name for n in await power.get_properties()] == [
            "EngineeringUnits"
        ]
        # Booleans, integers and texts are plain variables of their own type.
        for tag, dtype in (("ch0.enable", ua.ObjectIds.Boolean), ("scan.count", ua.ObjectIds.Int64),
                           ("ch0.mode", ua.ObjectIds.String)):  # fmt: skip
            node = c.get_node(ua.NodeId(tag, ns))
            assert await node.read_data_type() == ua.NodeId(dtype)
            assert await node.read_type_definition() == ua.NodeId(ua.ObjectIds.BaseDataVariableType)


async def test_operator_tags_are_writable_others_read_only(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        writable = ua.AccessLevel.CurrentWrite
        mode = await c.get_node(ua.NodeId("ch0.mode", ns)).get_access_level()
        voltage = await c.get_node(ua.NodeId("ch0.voltage", ns)).get_access_level()
        assert writable in mode
        assert writable not in voltage


async def test_the_channel_state_is_a_packml_style_state_machine(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        machine = c.get_node(ua.NodeId("/Bench/Channels/ch0/StateMachine", ns))
        current = await machine.get_child("0:CurrentState")
        assert current.nodeid == ua.NodeId("ch0.chain.state", ns)  # NodeIds stay tag names
        assert (await current.read_value()).Text == "Idle"
        number = await current.get_child("0:Number")
        assert number.nodeid == ua.NodeId("ch0.chain.state_code", ns)
        assert await number.read_value() == 2  # Idle in OPC UA's StateEnumeration numbering
        state = c.get_node(await (await current.get_child("0:Id")).read_value())
        assert (await state.read_browse_name()).Name == "Idle"
        number_of = await (await state.get_child("0:StateNumber")).read_value()
        assert number_of == 2
        fsm = c.get_node(await machine.read_type_definition())
        states = [(await n.read_browse_name()).Name for n in await fsm.get_children()]
        assert {"Stopped", "Idle", "Execute", "Held", "Unholding"} <= set(states)


async def test_timestamps_are_the_sample_time_and_the_scan_time(rig: Rig) -> None:
    db, clock = rig.bench.db, rig.bench.clock
    db.write("ch1.manual_current", 0.3)
    db.write("ch1.enable", True)
    tag = db["ch1.voltage"]
    changed_at = (tag.source_t, tag.server_t)
    try:
        for _ in range(10):  # charging: the cell voltage rises
            version = tag.version
            await rig.scans(1)
            if tag.version != version:  # a new value: its sample time and its scan's
                changed_at = (tag.source_t, tag.server_t)
        async with rig.client() as c:
            ns = await rig.ns(c)
            params = ua.ReadParameters()  # asyncua's read_data_value asks for Source only
            voltage = ua.ReadValueId(ua.NodeId("ch1.voltage", ns), ua.AttributeIds.Value)
            params.NodesToRead = [voltage]
            params.TimestampsToReturn = ua.TimestampsToReturn.Both
            (dv,) = await c.uaclient.read(params)
        assert dv.Value.Value == tag.value
        source_t, _ = changed_at
        assert dv.SourceTimestamp == datetime.fromtimestamp(clock.to_wall(source_t), UTC)
        # Part 4 §7.11: when the server last knew it current, the scan's last hand-over.
        heard_t = max(t.server_t for t in db)
        assert dv.ServerTimestamp == datetime.fromtimestamp(clock.to_wall(heard_t), UTC)
    finally:
        db.write("ch1.enable", False)
        db.write("ch1.manual_current", 0.0)
        await rig.scans(2)


async def test_quality_is_the_status_code_a_lost_board_is_a_communication_error(rig: Rig) -> None:
    async with rig.client() as c:
        ns = await rig.ns(c)
        temperature = await c.get_node(ua.NodeId("ch0.temperature", ns)).read_data_value(
            raise_on_bad_status=False
        )
        assert temperature.StatusCode.name == "BadOutOfService"  # no sensor on this board
        assert temperature.Value.Value is None
        sim = rig.bench.sim
        assert sim is not None
        boards = sim.devices["chadeche"]
        assert isinstance(boards, SimulatedBoards)
        boards.bus.fault = OSError("SPI bus unplugged")
        try:
            await rig.scans(20)
            dv = await c.get_node(ua.NodeId("ch0.voltage", ns)).read_data_value(
                raise_on_bad_status=False
            )
            assert rig.bench.db["ch0.voltage"].reason.value == "comm failure"
            assert dv.StatusCode.name == "BadCommunicationError"
            assert dv.Value.Value is None  # a Bad value is published as null (Part 4)
        finally:
            boards.bus.fault = None
            await rig.scans(30)
        dv = await c.get_node(ua.NodeId("ch0.voltage", ns)).read_data_value()
        assert dv.StatusCode.is_good()


async def test_a_subscription_gets_every_scan_s_changes(rig: Rig) -> None:
    got = Collector()
    async with rig.client(user="bob") as c:  # a viewer may subscribe
        ns = await rig.ns(c)
        sub = await c.create_subscription(20, got)
        await sub.subscribe_data_change(
            [c.get_node(ua.NodeId(t, ns)) for t in ("scan.count", "ch0.voltage")], queuesize=100
        )
        await eventually(lambda: bool(got.values("scan.count")), "the first value")
        (start,) = got.values("scan.count")
        for _ in range(5):
            await rig.scans(1)
        # The scan's own figures are set after its publishers ran: each shows at the next.
        wanted = list(range(start, start + 6))
        await eventually(lambda: got.values("scan.count") == wanted, "one update per scan")
        await sub.delete()
