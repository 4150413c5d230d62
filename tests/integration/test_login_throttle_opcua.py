"""Password guessing over OPC UA (issue 27, finding 4): the same throttle as HTTP (one per
bench), so wrong passwords beyond the limit are refused with Bad_UserAccessDenied, the
right password too while the delay runs, without the password being checked; another
user still logs in. asyncua clients against the real server (tests/opcuarig.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from asyncua import ua
from opcuarig import opcua_rig

from supervisor.app.logins import BURST_ALARM
from supervisor.core.logins import PAIR

pytestmark = pytest.mark.integration


async def test_wrong_passwords_beyond_the_limit_are_refused_even_with_the_right_one(
    tmp_path: Path,
) -> None:
    async with opcua_rig(tmp_path) as rig:
        users = rig.server.users
        for _ in range(PAIR.free):
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                async with rig.client("alice", "guess"):
                    pass
        checks = users.checks
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            async with rig.client("alice"):  # the right password, during the delay
                pass
        assert users.checks == checks  # refused before its password was checked
        assert rig.bench.logins is rig.server.throttle  # the bench's one, shared with HTTP
        assert rig.bench.logins.refused_tries == 1
        # Counted for the client's address (asyncua's session names its peer).
        assert ("alice", "127.0.0.1") in rig.bench.logins._pair.counts
        async with rig.client("carol") as c:  # another user
            assert await rig.ns(c) > 0
        assert rig.bench.alarms is not None and BURST_ALARM in rig.bench.alarms
