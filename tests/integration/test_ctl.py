"""``supervisor ctl`` against a real OPC UA server on loopback (opcuarig: the bench in
process on the virtual clock, scanning when the test says so). The command line runs on
its own thread, as a separate process would, so the server and the bench keep serving.

Security: Basic256Sha256 Sign and SignAndEncrypt with ctl's own certificate (made on first
use in ``$XDG_CONFIG_HOME/bench-supervisor/ctl-pki``, a temporary folder here) or one given
with ``--cert/--key``, refused until it is in the server's trust list; a server with its
None policy switched off. ``ack`` on real alarms (the e-stop pressed on the simulated bench,
a chain's supervision alarm); ``watch --every S --count N``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import io
import re
import stat
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from commandrig import SUPERVISED, recipe
from cryptography import x509
from opcuarig import PASSWORDS, Rig, client_certificate, opcua_rig, trust

from supervisor.chains.states import State
from supervisor.cli.main import main
from supervisor.publish.opcua import OpcUaSettings
from supervisor.testing import free_tcp_port, wait_until

pytestmark = pytest.mark.integration


@pytest.fixture(autouse=True)
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """ctl's per-user folder (its client certificate) in the test's own folder."""
    home = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))
    return home


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with opcua_rig(tmp_path) as r:
        yield r


async def ctl(
    rig: Rig | None,
    capsys: pytest.CaptureFixture[str],
    *argv: str,
    user: str | None = None,
    security: tuple[str, ...] = (),
) -> tuple[int, list[str], list[str]]:
    """``supervisor ctl --url <the rig's server> [--user …] [security] argv``: (exit code,
    out, err)."""
    url = rig.server.endpoint if rig is not None else "opc.tcp://127.0.0.1:1/supervisor"
    login = ["--user", user, "--password", PASSWORDS[user]] if user else []
    code = await asyncio.to_thread(main, ["ctl", "--url", url, *login, *security, *argv])
    out, err = capsys.readouterr()
    return code, out.splitlines(), err.splitlines()


async def test_status_shows_every_channel(rig: Rig, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = await ctl(rig, capsys, "status")
    assert (code, err) == (0, [])
    # Issue 26: what the channel does and its chain's state in two columns (the mode in
    # the first), and the test's charge (none before a recipe is loaded).
    assert re.split(r"\s{2,}", out[0]) == [
        "channel", "channel state", "chain", "recipe", "step", "V", "I (A)", "charge (Ah)",
    ]  # fmt: skip
    channels = [c.name for c in rig.bench.cfg.channels]
    assert [line.split()[0] for line in out[1:]] == channels
    ch0 = re.split(r"\s{2,}", out[1])
    assert ch0[1:3] == ["idle, manual", "Idle"]
    assert ch0[-3] == f"{rig.bench.db['ch0.voltage'].value:.3f}"
    assert ch0[-1] == "—"


async def test_start_runs_the_recipe_and_status_shows_its_step(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code, out, err = await ctl(rig, capsys, "start", "ch0", recipe(tmp_path), user="alice")
    assert (code, err) == (0, [])
    assert "recipe d loaded" in out[0] and "started" in out[0]
    await rig.scans(3)
    code, out, _ = await ctl(rig, capsys, "status")
    assert code == 0
    ch0 = re.split(r"\s{2,}", out[1])
    assert ch0[:5] == ["ch0", "discharging 0.200 A, auto", "Running", "d", "1 d"]
    assert float(ch0[-2]) == pytest.approx(-0.2, abs=0.01)  # discharging 200 mA
    assert float(ch0[-1]) == pytest.approx(0.0, abs=0.001)  # the test's charge, from 0
    command = rig.bench.commands.log[-1]
    assert (command.actor, command.accepted) == ("opcua:alice", True)


async def test_start_passes_its_parameters(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    text = (
        "recipe: p\nparameters: {v_min: 1.0 V}\nsteps:\n  - id: d\n    discharge: 200 mA\n"
        "    duration: 1 h\n    until: [{voltage <= v_min: next}]\n  - {id: r, rest: 1 h}\n"
    )
    code, _, err = await ctl(
        rig, capsys, "start", "ch0", recipe(tmp_path, text), "-p", "v_min=5 V", user="alice"
    )
    assert (code, err) == (0, [])
    await rig.scans(3)
    assert rig.bench.db["ch0.chain.step"].value == "r"  # above the cell: the step ended at once


async def test_start_gives_the_tests_cell_and_comment_through_the_opcua_start_method(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    argv = ("start", "ch0", recipe(tmp_path), "--cell", "NIMH-9", "--comment", "second life")
    code, _, err = await ctl(rig, capsys, *argv, "--capacity", "1300 mAh", user="alice")
    assert (code, err) == (0, [])
    await rig.scans(3)
    md = rig.bench.results["ch0"].metadata
    assert (md.cell_id, md.comment, md.operator) == ("NIMH-9", "second life", "opcua:alice")
    assert md.nominal_capacity_ah == pytest.approx(1.3)
    assert rig.bench.db["ch0.chain.cell_id"].value == "NIMH-9"


async def test_start_with_a_bad_cell_id_exits_2_naming_the_field(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    argv = ("start", "ch0", recipe(tmp_path), "--cell", "a;b")
    code, _, err = await ctl(rig, capsys, *argv, user="alice")
    assert code == 2 and "cell_id 'a;b' has ';'" in err[0], err


async def test_a_refused_command_exits_2_with_the_server_s_reason(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = await ctl(rig, capsys, "start", "ch0", "no-such-recipe", user="alice")
    assert (code, out) == (2, [])
    assert err == [
        "supervisor ctl: ch0: start refused (BadNotFound): no-such-recipe: no such recipe"
        f" in {rig.tmp}/"
    ]
    code, _, err = await ctl(rig, capsys, "hold", "ch0")  # anonymous: read only
    assert code == 2
    assert err == [
        "supervisor ctl: ch0: hold refused (BadUserAccessDenied): an anonymous session may"
        " only read (role viewer): log in as an operator"
    ]
    code, _, err = await ctl(rig, capsys, "abort", "ch9", user="alice")
    assert code == 2
    assert err[0].startswith("supervisor ctl: ch9: no such channel (channels: ch0, ")


async def test_the_isa88_commands_and_ack_reach_the_command_path(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert (await ctl(rig, capsys, "start", "ch1", recipe(tmp_path), user="alice"))[0] == 0
    await rig.scans(2)
    for verb in ("hold", "resume", "advance", "stop"):
        code, _, err = await ctl(rig, capsys, verb, "ch1", user="alice")
        assert (code, err) == (0, []), verb
        await rig.scans(3)
    assert (await ctl(rig, capsys, "reset", "ch1", user="alice"))[0] == 0
    code, _, err = await ctl(rig, capsys, "ack", "ch1", user="alice")
    assert code in (0, 2) and all("Traceback" not in e for e in err)
    kinds = [e.command.split()[0] for e in rig.bench.commands.log if e.actor == "opcua:alice"]
    assert kinds[:6] == ["start", "hold", "resume", "advance", "stop", "reset"]


async def test_alarms_lists_the_active_ones(rig: Rig, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = await ctl(rig, capsys, "alarms")
    assert (code, err) == (0, [])
    assert rig.bench.alarms is not None
    active = [a for a in rig.bench.alarms if a.active or not a.acked]
    assert active, "the rig's room is above its H limit"
    assert sorted(line.split()[0] for line in out) == sorted(a.id for a in active)


async def test_watch_prints_a_line_at_each_state_or_step_change(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    url = rig.server.endpoint
    watching = asyncio.create_task(
        asyncio.to_thread(
            main, ["ctl", "--url", url, "watch", "ch0", "--every", "600", "--lines", "2"]
        )
    )
    seen: list[str] = []

    def lines() -> int:
        seen.extend(capsys.readouterr().out.splitlines())
        return len(seen)

    await wait_until(lambda: lines() >= 1, "the first line (the subscription's initial values)")
    assert seen[0].startswith("ch0 C/00/00 mA=  0 ") and " Idle " in seen[0]
    assert (await ctl(rig, capsys, "start", "ch0", recipe(tmp_path), user="alice"))[0] == 0
    await rig.scans(3)
    assert await watching == 0
    lines()
    assert seen[1].startswith("ch0 D/") and " Running d, " in seen[1]


async def test_an_unreachable_server_exits_1_with_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    url = f"opc.tcp://127.0.0.1:{free_tcp_port()}/supervisor"
    code = await asyncio.to_thread(main, ["ctl", "--url", url, "status"])
    out, err = capsys.readouterr()
    assert (code, out) == (1, "")
    assert err.splitlines() == [err.strip()] and err.startswith(
        f"supervisor ctl: cannot reach {url}: "
    )


async def test_a_wrong_password_exits_2_with_one_line(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["ctl", "--url", rig.server.endpoint, "--user", "alice", "--password", "nope", "status"]
    code = await asyncio.to_thread(main, argv)
    out, err = capsys.readouterr()
    assert (code, out) == (2, "")
    assert err.splitlines() == [
        f"supervisor ctl: {rig.server.endpoint}: the server refused the login of user 'alice'"
        " (BadUserAccessDenied): check --user and the password"
    ]


async def test_the_password_may_come_from_the_environment(
    rig: Rig, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("SUPERVISOR_OPCUA_PASSWORD", PASSWORDS["alice"])
    argv = [
        "ctl",
        "--url",
        rig.server.endpoint,
        "--user",
        "alice",
        "start",
        "ch0",
        recipe(tmp_path),
    ]
    assert await asyncio.to_thread(main, argv) == 0
    assert rig.bench.commands.log[-1].actor == "opcua:alice"


async def test_the_password_may_come_from_standard_input_and_stays_off_the_command_line(
    rig: Rig, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("SUPERVISOR_OPCUA_PASSWORD", raising=False)
    monkeypatch.setattr("sys.stdin", io.StringIO(PASSWORDS["alice"] + "\n"))
    argv = ["ctl", "--url", rig.server.endpoint, "--user", "alice", "--password-stdin"]
    assert await asyncio.to_thread(main, [*argv, "start", "ch0", recipe(tmp_path)]) == 0
    assert rig.bench.commands.log[-1].actor == "opcua:alice"
    assert PASSWORDS["alice"] not in argv


def test_password_stdin_without_a_user_or_with_password_is_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["ctl", "--password-stdin", "status"]) == 2
    assert main(["ctl", "--user", "a", "--password", "x", "--password-stdin", "status"]) == 2
    err = capsys.readouterr().err
    assert "--password-stdin needs --user" in err
    assert "not allowed with argument" in err
    assert "Traceback" not in err


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "bogus"]) == 2
    assert main(["ctl", "start", "ch0"]) == 2  # no recipe
    assert main(["ctl", "watch", "--every", "0"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(e.startswith("supervisor ctl") for e in err)


# --- security: Basic256Sha256 Sign and SignAndEncrypt -------------------------------------
def own_certificate(config_home: Path) -> Path:
    return config_home / "bench-supervisor" / "ctl-pki" / "cert.der"


async def test_a_certificate_made_on_first_use_is_refused_until_the_server_trusts_it(
    rig: Rig, capsys: pytest.CaptureFixture[str], config_home: Path
) -> None:
    secure = ("--security", "sign_and_encrypt")
    code, out, err = await ctl(rig, capsys, "status", security=secure)
    cert = own_certificate(config_home)
    url = rig.server.endpoint
    assert (code, out) == (1, [])
    assert err == [
        f"supervisor ctl: made this client's certificate {cert}: a server accepts it once it"
        " is copied into its pki/trusted (<state_dir>/opcua/pki/trusted)",
        f"supervisor ctl: {url}: the server refused this client's certificate"
        f" (BadCertificateUntrusted): copy {cert} into the server's pki/trusted"
        " (<state_dir>/opcua/pki/trusted; it keeps the refused one in pki/rejected) and run"
        " again",
    ]
    key = cert.parent / "key.pem"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    rejected = list((rig.settings.pki_dir / "rejected").iterdir())
    assert [r.read_bytes() for r in rejected] == [cert.read_bytes()]  # the very same file
    made = cert.read_bytes()
    trust(rig, cert)  # what the message says to do
    for mode in ("sign_and_encrypt", "sign"):
        code, out, err = await ctl(rig, capsys, "status", security=("--security", mode))
        assert (code, err) == (0, []), mode  # the same certificate: nothing made again
        assert [line.split()[0] for line in out[1:]] == [c.name for c in rig.bench.cfg.channels]
    assert cert.read_bytes() == made
    code, out, err = await ctl(rig, capsys, "start", "ch0", "nope", user="alice", security=secure)
    assert (code, err) == (
        2,
        [f"supervisor ctl: ch0: start refused (BadNotFound): nope: no such recipe in {rig.tmp}/"],
    )


def test_ctl_cert_prints_the_certificate_to_trust(
    capsys: pytest.CaptureFixture[str], config_home: Path
) -> None:
    assert main(["ctl", "cert"]) == 0
    out, err = capsys.readouterr()
    cert = own_certificate(config_home)
    assert out.splitlines() == [str(cert)] and err.startswith("supervisor ctl: made ")
    der = x509.load_der_x509_certificate(cert.read_bytes())
    san = der.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    (uri,) = san.get_values_for_type(x509.UniformResourceIdentifier)
    assert uri.startswith("urn:") and uri.endswith(":bench-supervisor:ctl")
    assert main(["ctl", "cert"]) == 0
    assert capsys.readouterr() == (f"{cert}\n", "")  # made once


async def test_a_given_certificate_and_key_are_used_and_refused_until_trusted(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path, config_home: Path
) -> None:
    cert, key = await client_certificate(tmp_path)
    given = ("--security", "sign", "--cert", str(cert), "--key", str(key))
    code, _, err = await ctl(rig, capsys, "status", security=given)
    assert code == 1 and len(err) == 1
    assert "(BadCertificateUntrusted): copy " + str(cert) + " into the server's" in err[0]
    trust(rig, cert)
    code, _, err = await ctl(rig, capsys, "hold", "ch0", user="alice", security=given)
    assert code == 2 and "hold refused (BadInvalidState)" in err[0]  # connected: a refusal
    assert not own_certificate(config_home).exists()  # none made


async def test_without_the_none_policy_ctl_says_to_use_security(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], config_home: Path
) -> None:
    def secure_only(s: OpcUaSettings) -> OpcUaSettings:
        return dataclasses.replace(s, security=("sign_and_encrypt",), anonymous=False)

    async with opcua_rig(tmp_path, change=secure_only) as rig:
        url = rig.server.endpoint
        code, out, err = await ctl(rig, capsys, "status", user="alice")
        assert (code, out) == (2, [])
        assert err == [
            f"supervisor ctl: {url}: the server accepts no unsecured connection (its None"
            " policy is switched off; it offers sign_and_encrypt): use --security"
            " sign_and_encrypt"
        ]
        code, _, err = await ctl(
            rig, capsys, "status", user="alice", security=("--security", "sign")
        )
        assert code == 2
        assert err[-1] == (
            f"supervisor ctl: {url}: the server offers no Basic256Sha256 sign endpoint (it"
            " offers sign_and_encrypt): change --security"
        )
        trust(rig, own_certificate(config_home))
        secure = ("--security", "sign_and_encrypt")
        code, _, err = await ctl(rig, capsys, "status", security=secure)  # anonymous: off
        assert code == 2
        assert err == [
            f"supervisor ctl: {url}: the server refused the login of an anonymous session"
            " (BadIdentityTokenRejected): check --user and the password"
        ]
        code, out, err = await ctl(
            rig, capsys, "start", "ch0", recipe(tmp_path), user="alice", security=secure
        )
        assert (code, err) == (0, []) and "started" in out[0]
        assert rig.bench.commands.log[-1].actor == "opcua:alice"


def test_security_usage_errors_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, config_home: Path
) -> None:
    cert = tmp_path / "c.der"
    cert.write_bytes(b"not a certificate")
    assert main(["ctl", "--security", "tls", "status"]) == 2
    assert main(["ctl", "--security", "sign", "--cert", str(cert), "status"]) == 2
    assert main(["ctl", "--cert", str(cert), "--key", str(cert), "status"]) == 2  # security none
    missing = tmp_path / "missing.der"
    assert (
        main(["ctl", "--security", "sign", "--cert", str(missing), "--key", str(cert), "status"])
        == 2
    )
    assert (
        main(["ctl", "--security", "sign", "--cert", str(cert), "--key", str(cert), "status"]) == 2
    )
    assert main(["ctl", "watch", "--count", "-1"]) == 2
    err = capsys.readouterr().err.splitlines()
    usage = [e for e in err if not e.startswith("usage:") and not e.startswith("  ")]
    assert usage == [
        "supervisor ctl: argument --security: invalid choice: 'tls' (choose from 'none',"
        " 'sign', 'sign_and_encrypt') (see supervisor ctl --help)",
        "supervisor ctl: --cert and --key go together: give both, or neither for the"
        f" certificate ctl makes in {config_home / 'bench-supervisor' / 'ctl-pki'}",
        "supervisor ctl: --cert/--key are used with --security sign or sign_and_encrypt",
        f"supervisor ctl: --cert {missing}: no such file",
        f"supervisor ctl: --cert {cert}: not a certificate (DER or PEM): "
        + usage[4].split("(DER or PEM): ", 1)[-1],
        "supervisor ctl watch: argument --count/--lines: '-1': give 0 (no end) or a"
        " positive count (see supervisor ctl watch --help)",
    ]
    assert not (config_home / "bench-supervisor").exists()


# --- ack on real alarms ------------------------------------------------------------------
async def test_ack_acknowledges_the_estop_alarm_in_the_alarm_model(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    alarms, sim = rig.bench.alarms, rig.bench.sim
    assert alarms is not None and sim is not None
    sim.press_estop(True)
    await rig.scans(5)
    code, out, _ = await ctl(rig, capsys, "alarms")
    assert code == 0
    assert (
        "estop  active, unacknowledged  severity 900  Emergency stop pressed (e-stop circuit open)"
        in "\n".join(out)
    )
    code, _, err = await ctl(rig, capsys, "ack", "estop")  # anonymous: read only
    assert code == 2 and err == ["supervisor ctl: estop: ack refused (BadUserAccessDenied)"]
    assert not alarms["estop"].acked
    code, out, err = await ctl(rig, capsys, "ack", "estop", user="alice")
    assert (code, err) == (0, [])
    assert out == ["estop: acknowledged (active, acknowledged)"]
    assert alarms["estop"].acked and alarms["estop"].active
    last = alarms.history[-1]
    assert (last.alarm_id, last.transition.value, last.actor) == (
        "estop",
        "acknowledged",
        "opcua:alice",
    )
    code, _, err = await ctl(rig, capsys, "ack", "estop", user="alice")
    assert code == 2
    assert err == [
        "supervisor ctl: estop: ack refused (BadConditionBranchAlreadyAcked): nothing to"
        " acknowledge"
    ]
    sim.press_estop(False)
    await rig.scans(5)
    code, out, _ = await ctl(rig, capsys, "alarms")
    assert code == 0 and not any(line.startswith("estop ") for line in out)
    code, _, err = await ctl(rig, capsys, "ack", "nothing", user="alice")
    assert code == 2 and err[0].startswith("supervisor ctl: nothing: no such channel or alarm")


async def test_ack_on_a_channel_acknowledges_its_chain_alarm_so_it_may_resume(
    rig: Rig, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code, _, _ = await ctl(rig, capsys, "start", "ch0", recipe(tmp_path, SUPERVISED), user="alice")
    assert code == 0
    await rig.scans(120)  # past the step's 10 s supervision at 0.1 s per scan
    assert rig.bench.runners["ch0"].state is State.HELD
    code, _, err = await ctl(rig, capsys, "resume", "ch0", user="alice")
    assert code == 2 and "acknowledge the alarm first" in err[0]
    code, out, err = await ctl(rig, capsys, "ack", "ch0", user="alice")
    assert (code, err) == (0, [])
    assert out[0].startswith("ch0: chain alarm acknowledged (supervision: step c exceeded")
    code, _, err = await ctl(rig, capsys, "resume", "ch0", user="alice")
    assert (code, err) == (0, [])
    await rig.scans(2)
    assert rig.bench.runners["ch0"].state is State.RUNNING


# --- watch --every S --count N -----------------------------------------------------------
DISPLAY_LINE = re.compile(
    r"ch0 C/00/00 mA=  0 SET= 0 TET= 0 V=\d+\.\d{3} mAh=— Idle —,"  # no recipe, no charge
    r" \w{3} \w{3} \d\d \d\d:\d\d:\d\d \d{4}"
)


async def test_watch_every_prints_a_line_each_period_and_count_ends_it(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    # The bench does not scan: nothing changes, so every line after the first (the
    # subscription's initial values) is the periodic one. Wall time: watch's period is the
    # client's own clock (0.1 s here), as on a bench.
    argv = ["ctl", "--url", rig.server.endpoint, "watch", "ch0", "--every", "0.1", "--count", "4"]
    assert await asyncio.to_thread(main, argv) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert err == "" and len(lines) == 4
    assert all(DISPLAY_LINE.fullmatch(line) for line in lines), lines


async def test_watch_ends_with_exit_1_when_the_server_goes_away(
    rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    url = rig.server.endpoint
    watching = asyncio.create_task(
        asyncio.to_thread(main, ["ctl", "--url", url, "watch", "ch0", "--every", "600"])
    )
    seen: list[str] = []

    def lines() -> int:
        seen.extend(capsys.readouterr().out.splitlines())
        return len(seen)

    await wait_until(lambda: lines() >= 1, "the first line")
    await rig.server.stop()
    assert await watching == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"supervisor ctl: {url}: connection lost")
