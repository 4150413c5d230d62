"""Every command of the command path goes into the audit trail (issue 34): accepted or
refused with its reason, from whichever client — acknowledges, shelves, forces and the
software e-stop included, since they are commands of the one path (ADR 0008). The log
never stands in a command's way: an entry that cannot be written is counted, and the
command is answered as before."""

from __future__ import annotations

from pathlib import Path

from supervisor.app.bench import Bench
from supervisor.audit import AUDIT_NAME, AuditLog, read_entries
from supervisor.commands import Command, Verb


def _audited(bench: Bench, path: Path) -> AuditLog:
    audit = AuditLog(path, wall=bench.clock.wall).open()
    bench.commands.audit = audit
    return audit


async def test_every_command_accepted_or_refused_is_an_entry_with_its_actor(
    bench: Bench, tmp_path: Path
) -> None:
    audit = _audited(bench, tmp_path / AUDIT_NAME)
    c = bench.commands
    c.execute(Command.channel("ch0", Verb.HOLD, "hmi:otto"))  # refused: nothing runs
    c.execute(Command.alarm("room.temp.H", Verb.SHELVE, "opcua:olga", duration_s=600))
    c.execute(Command.alarm("room.temp.H", Verb.UNSHELVE, "opcua:olga"))
    c.execute(Command.force("room.temp", 21.5, "hmi:otto"))  # an operator: refused
    c.execute(Command.estop("modbus:plc"))
    c.execute(Command.channel("ch0", Verb.ACKNOWLEDGE, "hmi:otto"))
    c.execute(Command.estop_reset("cli"))
    assert audit.flush()
    audit.close()
    got = [
        (e.actor, e.kind, e.target, e.details_json["accepted"]) for e in read_entries(audit.path)
    ]
    assert got == [
        ("hmi:otto", "command.hold", "ch0", False),
        ("opcua:olga", "command.shelve", "alarm room.temp.H", True),
        ("opcua:olga", "command.unshelve", "alarm room.temp.H", True),
        ("hmi:otto", "command.force", "bench", False),
        ("modbus:plc", "command.estop", "bench", True),
        ("hmi:otto", "command.acknowledge", "ch0", got[5][3]),
        ("cli", "command.estop_reset", "bench", got[6][3]),
    ]
    first = read_entries(audit.path)[0].details_json
    assert first["result"] == "refused" and first["reason"] == c.log[0].reason
    assert first["command"] == "hold" and first["channel"] == "ch0"


async def test_an_audit_log_that_cannot_write_never_changes_a_commands_answer(
    bench: Bench, tmp_path: Path
) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    audit = AuditLog(blocker / AUDIT_NAME, retry_s=60.0)
    audit.open()
    bench.commands.audit = audit
    res = bench.commands.execute(
        Command.alarm("room.temp.H", Verb.SHELVE, "hmi:otto", duration_s=6)
    )
    assert res.accepted
    assert not audit.flush(timeout_s=5.0)
    assert audit.failures == 1 and audit.pending == 1 and "File exists" in str(audit.error)
    audit.close(timeout_s=5.0)
