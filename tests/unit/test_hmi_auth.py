"""HMI sessions and roles without a server: sessions expire after their timeout of
inactivity (injected time), the role hook answers ``hmi:<user>`` from the users file, and an
I/O map that would let anyone on the network operate is refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from aiohttp import web
from commandrig import chadeche_map

from supervisor.cli.main import main
from supervisor.commands import Command, Verb
from supervisor.commands.roles import EveryoneOperates
from supervisor.config.models import HmiConfig, is_loopback
from supervisor.config.users import User, UserStore, add_user
from supervisor.hmi.auth import (
    ANONYMOUS_VIEWER,
    PRINCIPAL_KEY,
    HmiRoles,
    Principal,
    Sessions,
    SessionsFull,
    refuse_unless,
)
from supervisor.tags import Access


class Now:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_a_session_lives_while_used_and_expires_after_the_timeout_unused() -> None:
    now = Now()
    sessions = Sessions(timeout_s=60.0, now=now)
    s = sessions.open(User("otto", "operator"))
    now.t += 59.0
    assert sessions.get(s.token) is s  # used: renewed
    now.t += 59.0
    assert sessions.expires_s(s) == pytest.approx(1.0)
    assert sessions.get(s.token) is s
    now.t += 60.0
    assert sessions.get(s.token) is None
    assert len(sessions) == 0


def test_looking_without_touching_does_not_renew_a_session() -> None:
    now = Now()
    sessions = Sessions(timeout_s=60.0, now=now)
    s = sessions.open(User("otto", "operator"))
    now.t += 50.0
    assert sessions.get(s.token, touch=False) is s
    now.t += 10.0
    assert sessions.get(s.token) is None


def test_tokens_are_unguessable_and_unknown_ones_find_nothing() -> None:
    sessions = Sessions(timeout_s=60.0, now=Now())
    a, b = sessions.open(User("otto", "operator")), sessions.open(User("otto", "operator"))
    assert a.token != b.token and len(a.token) >= 40
    assert sessions.get("guess") is None and sessions.get(None) is None and sessions.get("") is None


def test_sessions_are_bounded_a_full_table_of_other_users_refuses_rather_than_evicts() -> None:
    now = Now()
    sessions = Sessions(timeout_s=60.0, now=now, max_sessions=2)
    first = sessions.open(User("a", "viewer"))
    second = sessions.open(User("b", "operator"))
    with pytest.raises(SessionsFull, match="2 sessions are open, the most this bench keeps"):
        sessions.open(User("c", "viewer"))
    assert sessions.get(first.token) is first and sessions.get(second.token) is second
    now.t += 30.0
    sessions.get(second.token)
    now.t += 30.0  # the first expired: its room is taken back
    third = sessions.open(User("c", "viewer"))
    assert sessions.get(third.token) is third and sessions.get(second.token) is second


def test_a_user_past_their_session_limit_closes_their_own_oldest_never_another_users() -> None:
    sessions = Sessions(timeout_s=60.0, now=Now(), max_sessions=10, per_user=3)
    operator = sessions.open(User("otto", "operator"))
    opened = [sessions.open(User("vera", "viewer")) for _ in range(1001)]
    assert sessions.get(operator.token) is operator
    assert [sessions.get(s.token) for s in opened[-3:]] == opened[-3:]
    assert all(sessions.get(s.token) is None for s in opened[:-3])
    assert len(sessions) == 4


@pytest.fixture
def users(tmp_path: Path) -> UserStore:
    path = tmp_path / "users.yaml"
    for name, role in (("vera", "viewer"), ("otto", "operator"), ("erin", "engineer")):
        add_user(path, name, role, name + "-pw")
    return UserStore(path)


def test_the_role_hook_answers_hmi_actors_from_the_users_file(users: UserStore) -> None:
    roles = HmiRoles(users, EveryoneOperates())
    start = Command.channel("ch0", Verb.START, "hmi:vera")
    assert roles.refuses(start) == (
        "viewer may not start ch0 (hmi:vera is a viewer): log in as an operator"
    )
    assert roles.refuses(Command.channel("ch0", Verb.START, "hmi:otto")) == ""
    assert roles.access_of("hmi:vera") is Access.READ_ONLY
    assert roles.access_of("hmi:otto") is Access.OPERATOR
    assert roles.access_of("hmi:erin") is Access.ENGINEER
    anonymous = roles.refuses(Command.channel("ch0", Verb.RESET, "hmi:anonymous"))
    assert anonymous.startswith("viewer may not reset ch0 (not logged in)")
    write = Command.write("lab.setpoint", 1.0, "hmi:vera")
    assert roles.refuses(write) == (
        "viewer may not write lab.setpoint (hmi:vera is a viewer): log in as an operator"
    )
    # A user removed since they logged in is a viewer from then on.
    assert roles.access_of("hmi:gone") is Access.READ_ONLY


def test_other_actors_keep_the_hook_they_had(users: UserStore) -> None:
    roles = HmiRoles(users, EveryoneOperates())
    assert roles.refuses(Command.channel("ch0", Verb.START, "command line")) == ""
    assert roles.access_of("opcua:someone") is Access.OPERATOR


def test_the_hmi_settings_have_their_defaults() -> None:
    cfg = HmiConfig()
    assert (cfg.login, cfg.anonymous_read) == (False, True)
    assert cfg.session_timeout_s == 8 * 3600.0
    assert cfg.publish_period_s == 0.2


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.10", "::", "bench.lab"])
def test_login_off_on_a_non_loopback_host_is_refused(host: str) -> None:
    with pytest.raises(ValueError, match="not loopback and login is false"):
        HmiConfig(host=host, login=False)
    assert HmiConfig(host=host, login=True).login


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.1.1", "localhost", "::1"])
def test_loopback_hosts_need_no_login(host: str) -> None:
    assert is_loopback(host)
    assert not HmiConfig(host=host).login


def test_supervisor_run_refuses_login_off_on_the_network_with_one_message_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = yaml.safe_load(Path(chadeche_map(tmp_path)).read_text(encoding="utf-8"))
    data["hmi"] = {"host": "0.0.0.0", "port": 0, "login": False}
    path = tmp_path / "open.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert main(["run", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"{path}:")
    assert "host '0.0.0.0' is not loopback and login is false" in err[0]


def test_routes_that_are_not_commands_check_the_role_with_refuse_unless() -> None:
    from aiohttp.test_utils import make_mocked_request

    def request(p: Principal | None) -> web.Request:
        r = make_mocked_request("PUT", "/api/recipes/x")
        if p is not None:
            r[PRINCIPAL_KEY] = p
        return r

    session = Sessions(60.0, Now()).open(User("erin", "engineer"))
    engineer = Principal("erin", "engineer", "hmi:erin", session)
    operator = Principal("otto", "operator", "hmi:otto", session)
    assert refuse_unless(request(engineer), "engineer", "save recipes") is None
    refused = refuse_unless(request(operator), "engineer", "save recipes")
    assert refused is not None and refused.status == 403
    assert json.loads(refused.text or "") == {
        "accepted": False,
        "reason": "operator may not save recipes: log in as an engineer",
    }
    anonymous = refuse_unless(request(ANONYMOUS_VIEWER), "engineer", "save recipes")
    assert anonymous is not None and anonymous.status == 401
    assert refuse_unless(request(None), "engineer", "save recipes") is None  # login off
