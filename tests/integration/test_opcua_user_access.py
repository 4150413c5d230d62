"""Per-user access over OPC UA: a variable's UserAccessLevel and a method's UserExecutable
say what the session's role may do (docs/adr/0015-forcing-shelving-over-opcua.md), while
AccessLevel and Executable say what the node allows anyone: a viewer sees CurrentRead only,
an operator CurrentWrite on operator tags, an engineer also on engineer tags; ForceTag is
executable for an engineer only. The writes and calls stay checked by the command path.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from asyncua import Client, ua
from opcuarig import Rig, opcua_rig

from supervisor.app import Bench
from supervisor.tags import Access, TagSpec

pytestmark = pytest.mark.integration
A = ua.AccessLevel
LIMIT = "ch0.limit_set.voltage_max"  # an engineer tag, added for the test


def add_limit(bench: Bench) -> None:
    spec = TagSpec(LIMIT, unit="V", range=(0.8, 1.9), access=Access.ENGINEER)
    bench.db.update(bench.db.add(spec), 1.8)


async def levels(rig: Rig, c: Client, tag: str) -> tuple[set[A], set[A]]:
    node = c.get_node(ua.NodeId(tag, await rig.ns(c)))
    return set(await node.get_access_level()), set(await node.get_user_access_level())


async def executable(rig: Rig, c: Client, method: str) -> tuple[bool, bool]:
    node = c.get_node(ua.NodeId(method, await rig.ns(c)))
    a = await node.read_attribute(ua.AttributeIds.Executable)
    u = await node.read_attribute(ua.AttributeIds.UserExecutable)
    return bool(a.Value.Value), bool(u.Value.Value)


async def test_user_access_level_follows_the_sessions_role(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path, prepare=add_limit) as rig:
        want = {  # user: (operator tag writable, engineer tag writable)
            "bob": (False, False),
            "alice": (True, False),
            "carol": (True, True),
        }
        for user, (operator_tag, engineer_tag) in want.items():
            async with rig.client(user) as c:
                for tag, may in (("ch0.manual_current", operator_tag), (LIMIT, engineer_tag)):
                    anyone, mine = await levels(rig, c, tag)
                    assert A.CurrentWrite in anyone and A.CurrentRead in anyone
                    assert A.CurrentRead in mine, (user, tag)
                    assert (A.CurrentWrite in mine) is may, (user, tag)
                # A read-only tag is read-only for everyone.
                anyone, mine = await levels(rig, c, "ch0.voltage")
                assert A.CurrentWrite not in anyone and A.CurrentWrite not in mine
        async with rig.client(None) as c:  # anonymous: a viewer
            _, mine = await levels(rig, c, "ch0.manual_current")
            assert A.CurrentWrite not in mine


async def test_user_executable_follows_the_sessions_role(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as rig:
        want = {  # user: (Start, ForceTag)
            "bob": (False, False),
            "alice": (True, False),
            "carol": (True, True),
        }
        for user, (start, force) in want.items():
            async with rig.client(user) as c:
                assert await executable(rig, c, "/Bench/Channels/ch0/Start") == (True, start)
                assert await executable(rig, c, "/Bench/ForceTag") == (True, force)
