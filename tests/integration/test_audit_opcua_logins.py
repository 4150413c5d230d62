"""OPC UA password logins go into the bench's audit trail as the HMI's do (issue 34):
``login`` and ``login.failed`` with the actor ``opcua:<user>`` and the client's address,
whether the server runs in the bench's process (a virtual clock's) or in its own (ADR
0029, what ``supervisor run`` does). asyncua clients against the real server."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from asyncua import ua
from opcuarig import opcua_rig

from supervisor.app.bench import Bench
from supervisor.audit import AUDIT_NAME, AuditLog, read_entries

pytestmark = pytest.mark.integration


def with_audit(bench: Bench) -> None:
    bench.audit = AuditLog(Path(bench.cfg.state_dir) / AUDIT_NAME, wall=bench.clock.wall).open()


@pytest.mark.parametrize("process", [False, True], ids=["in-process", "own-process"])
async def test_a_failed_and_a_good_opcua_login_are_entries(tmp_path: Path, process: bool) -> None:
    kw = {"real_clock": True, "process": True} if process else {}
    async with opcua_rig(tmp_path, prepare=with_audit, **kw) as rig:
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with rig.client("alice", "guess"):
                pass
        async with rig.client("alice") as c:
            assert await rig.ns(c) > 0
        audit = rig.bench.audit
        assert audit is not None
        for _ in range(100):  # the child's report comes over its pipe
            if audit.appended >= 2:
                break
            await asyncio.sleep(0.05)
        assert audit.flush()
        got = [(e.actor, e.kind, e.target, e.details_json) for e in read_entries(audit.path)]
        audit.close()
    assert got == [
        ("opcua:alice", "login.failed", "alice", {"address": "127.0.0.1"}),
        ("opcua:alice", "login", "alice", {"address": "127.0.0.1"}),
    ]
