"""Issue 28, finding 1, over OPC UA: asyncua decodes a client's string with
``surrogateescape``, so a byte that is not UTF-8 (0xFF) arrives as a lone surrogate
(``"\\udcff"``). A method call carrying one is refused, and its refusal's event (which
quotes the value) is stored escaped by the real historian, which goes on writing (before,
that event killed its writer thread for good).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import ua
from opcuarig import Rig, call, opcua_rig

pytestmark = pytest.mark.integration
VT = ua.VariantType


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path, history=True) as r:
        yield r


async def test_a_method_argument_that_is_not_utf8_is_refused_and_history_goes_on(
    rig: Rig,
) -> None:
    historian = rig.bench.historian
    assert historian is not None
    async with rig.client("alice") as c:
        ns = await rig.ns(c)
        node = ua.NodeId("/Bench/Channels/ch1", ns)
        res = await call(
            c, node, ua.NodeId("/Bench/Channels/ch1/SetMode", ns), ua.Variant("x\udcff", VT.String)
        )
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    await rig.scans(3)
    assert await asyncio.to_thread(historian.writer.flush)
    written = historian.writer.rows_written
    await rig.scans(3)
    assert await asyncio.to_thread(historian.writer.flush)
    assert historian.writer.rows_written > written
    assert (historian.writer.crashes, historian.writer.write_errors) == (0, 0)
    texts = [e.text for e in historian.query.events(0, 4e9, kind="command")]
    assert any("x\\udcff" in t for t in texts), texts
