"""The standard address space read from its shelf (ADR 0020) is the one asyncua builds in
memory: the same nodes answer with the same attributes and references; only the nodes
something asked for are kept in memory; a bench's server starts from the shared shelf."""

from __future__ import annotations

from pathlib import Path

import pytest
from asyncua import Server, ua
from opcuarig import opcua_rig

from supervisor.publish.opcua import shelf

pytestmark = pytest.mark.integration
O = ua.ObjectIds  # noqa: E741

SAMPLE = (
    O.RootFolder,
    O.Server,
    O.Server_ServerStatus,
    O.Server_ServerStatus_State,
    O.BaseDataVariableType,
    O.AlarmConditionType,
    O.AlarmConditionType_ShelvingState,
    O.AcknowledgeableConditionType_Acknowledge,
    O.AnalogItemType_EURange,
    O.HasComponent,
    O.Double,
)


async def describe(server: Server, node_id: int) -> tuple[object, ...]:
    node = server.get_node(ua.NodeId(node_id))
    refs = await node.get_references(refs=ua.ObjectIds.References)
    return (
        await node.read_browse_name(),
        await node.read_node_class(),
        await node.read_display_name(),
        sorted((r.ReferenceTypeId.to_string(), r.NodeId.to_string(), r.IsForward) for r in refs),
    )


@pytest.fixture(scope="module")
def built_shelf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A shelf built for real (asyncua in a child process, a few seconds)."""
    root = tmp_path_factory.mktemp("cache")
    path = shelf.shelf_path(root)
    shelf.build_shelf(path)
    assert shelf.ready(path)
    return path


async def test_the_shelved_space_answers_as_the_space_in_memory(built_shelf: Path) -> None:
    in_memory, shelved = Server(), Server()
    await in_memory.init()
    await shelved.init(shelf_file=built_shelf)
    for nid in SAMPLE:
        assert await describe(shelved, nid) == await describe(in_memory, nid), nid


async def test_only_the_nodes_asked_for_are_in_memory(built_shelf: Path) -> None:
    server = Server()
    await server.init(shelf_file=built_shelf)
    held = len(server.iserver.aspace._nodes)  # the nodes read from the shelf so far
    assert held < 200  # of the 6174 standard nodes
    await describe(server, O.AlarmConditionType)
    assert len(server.iserver.aspace._nodes) > held


async def test_a_bench_server_starts_from_the_shared_shelf(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, built_shelf: Path
) -> None:
    monkeypatch.setenv(shelf.CACHE_ENV, str(built_shelf.parent.parent))
    async with opcua_rig(tmp_path) as rig:
        inner = rig.server._server
        assert inner is not None
        assert len(inner.iserver.aspace._nodes) < 6174
        async with rig.client() as c:
            status = c.get_node(ua.NodeId(O.Server_ServerStatus_State))
            assert await status.read_value() == ua.ServerState.Running
            types = await c.get_node(ua.NodeId(O.BaseEventType)).get_children()
            assert ua.NodeId(O.ConditionType) in [t.nodeid for t in types]
