"""``supervisor fleet``'s usage errors (exit 2, said on stderr) come before any connection
or listener: a broker that is not mqtt://HOST:PORT, a group or host id that is not one
topic level, an address that is not HOST:PORT, another address than loopback without a
users file."""

from __future__ import annotations

import pytest

from supervisor.cli.main import main

OK = ["fleet", "--broker", "mqtt://127.0.0.1:1883", "--group", "Lab"]


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["fleet", "--broker", "http://x:1", "--group", "Lab"], "mqtt://host:port"),
        (["fleet", "--broker", "mqtt://x:1", "--group", "La/b"], "group"),
        ([*OK, "--host-id", "a+b"], "--host-id"),
        ([*OK, "--listen", "8090"], "expected HOST:PORT"),
        ([*OK, "--listen", "10.0.0.5:8090"], "without --users"),
        ([*OK, "--listen", "0.0.0.0:0"], "without --users"),
    ],
)
def test_a_usage_error_is_refused_with_its_reason(
    args: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(args) == 2
    assert said in capsys.readouterr().err
