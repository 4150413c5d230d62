"""The one command path (docs/design.md "Safety"): every operator command is checked — role,
target, arguments, state, interlocks — executed, recorded with its actor, and answered
accepted or refused with the reason.

Checks, in order:

1. **role** (``Roles``: everyone operates until there are users) → forbidden;
2. **target**: the channel, alarm or tag exists → not found;
3. **arguments**: their names, types and values → bad argument;
4. **state**: the chain's ISA-88 table and its guards (``chains.states.decide``), and Auto
   vs Manual (a manual setpoint or enable is refused while the chain drives the channel)
   → refused;
5. **interlocks**: a channel held by a trip, or with an unacknowledged alarm, refuses
   ``start``, ``resume`` and ``enable on``, naming the alarm (ISA-18.2 / S7-GRAPH: alarms
   are acknowledged before running again) → refused.

Mode changes are explicit commands, never side effects (ISA-88 / PLC practice: bumpless
transfer). Switching to Manual while a chain runs holds the chain first, and Manual starts
at 0 A with enable off — or, with ``keep_setpoint``, from the present setpoint with the
power stage as it was. ``start`` hands the channel to its chain (Auto), and resetting a
finished test gives it back (Manual, enable off, 0 A; ``ChainRunner``).

Every command is recorded: a ``CommandEvent`` in a bounded log, logged with its context,
handed to the listeners, and into the chain's events of the channel it concerns (so the
result files' timeline holds the commands of a running test).

Commands run on the event loop between two scans (the scan is synchronous), so a command
sees one consistent process image and its effect is taken by the next scan. The one part
that can take seconds — reading, parsing and compiling a recipe to load — runs in a worker
thread for clients on the running loop (``execute_async``: the HTTP API, ``supervisor
run``), bounded by ``RECIPE_COMPILE_TIMEOUT_S``; only applying the compiled program comes
back to the loop. ``execute`` does the same in one go where no scan runs (tests, tools).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from supervisor.audit import AuditLog
from supervisor.chains.engine import ChainRunner
from supervisor.chains.states import MANUAL_DRIVEN, State, check_load, decide
from supervisor.channels import Mode
from supervisor.commands.force import channel_safety_tags, parse_forced
from supervisor.commands.model import (
    ALARM_VERBS,
    BENCH_VERBS,
    CHAIN_VERBS,
    CHANNEL_BAR,
    CHANNEL_VERBS,
    ESTOP_VERBS,
    Command,
    CommandEvent,
    Result,
    ResultKind,
    Target,
    TargetKind,
    Verb,
)
from supervisor.commands.recipes import (
    PreparedRecipe,
    RecipeFolders,
    RecipeLoader,
    RecipeNotFound,
    RecipeOutside,
    compile_recipe_file,
)
from supervisor.commands.roles import EveryoneOperates, Roles
from supervisor.commands.worker import WorkerTimeout, run_in_worker
from supervisor.config.limits import RECIPE_COMPILE_TIMEOUT_S
from supervisor.core.clock import Clock
from supervisor.core.errors import ConfigError, ConfigErrors, OperatorError
from supervisor.publish.provenance import METADATA_ARGUMENTS, MetadataError, metadata_from_arguments
from supervisor.safety import AlarmManager, ChannelGuard, Estop
from supervisor.tags import Access, TagDB
from supervisor.tags.spec import clipped_repr, finite_float

log = logging.getLogger(__name__)

LOG_LENGTH = 1000
RECIPE_ARGUMENTS = ("recipe", "parameters", *METADATA_ARGUMENTS)
"""What a load or a start may be given: the recipe, its parameters and the test's metadata."""
"""Commands kept in memory (the chain events and the result files keep theirs)."""

# A channel's operator tags that are commands: their writes take the command's checks.
CHANNEL_COMMAND_TAGS = ("command", "mode", "manual_current", "enable", "ack")
IN_AUTO = "channel {ch} is in auto (step chain): switch to manual first"
NO_LOADER = "this bench does not load recipes"
RUNNING = (State.RUNNING, State.RESUMING)


class Refusal(Exception):
    """Raised by a check: the command is refused, of this kind, for this reason."""

    def __init__(self, kind: ResultKind, reason: str, details: tuple[str, ...] = ()) -> None:
        super().__init__(reason)
        self.kind = kind
        self.reason = reason
        self.details = details


class CommandPath:
    """``execute(Command) -> Result``, for every client of a bench."""

    def __init__(
        self,
        db: TagDB,
        clock: Clock,
        runners: Mapping[str, ChainRunner] | None = None,
        guards: Mapping[str, ChannelGuard] | None = None,
        alarms: AlarmManager | None = None,
        loader: RecipeLoader | None = None,
        roles: Roles | None = None,
        compile_timeout_s: float = RECIPE_COMPILE_TIMEOUT_S,
        protected: Mapping[str, str] | None = None,
        recipe_folders: RecipeFolders | None = None,
        estop: Estop | None = None,
    ) -> None:
        self.db = db
        self.clock = clock
        self.runners: Mapping[str, ChainRunner] = runners or {}
        self.guards: Mapping[str, ChannelGuard] = guards or {}
        self.alarms = alarms
        self.loader = loader
        self.roles: Roles = roles or EveryoneOperates()
        self.compile_timeout_s = compile_timeout_s
        # Where a recipe may be loaded from (None: anywhere — tools and tests without a
        # network client; a bench always has its I/O map's folders). Commands given in
        # this host's shell (``Command.local``) read what that shell's user can read.
        self.recipe_folders = recipe_folders
        # The bench's e-stop (safety.estop): its software button (``estop``, ``estop_reset``).
        self.estop = estop
        # Tags a force may never touch → what reads them (commands/force.py); without the
        # bench's list, at least every channel guard's.
        self.protected: Mapping[str, str] = (
            protected
            if protected is not None
            else {t: w for g in self.guards.values() for t, w in channel_safety_tags(g.cfg).items()}
        )
        self.log: deque[CommandEvent] = deque(maxlen=LOG_LENGTH)
        self.listeners: list[Callable[[CommandEvent], None]] = []
        # The bench's audit trail (supervisor.audit): every command, accepted or refused.
        self.audit: AuditLog | None = None
        # Channel -> the recipe file its worker is compiling (one load at a time each).
        self._loading: dict[str, str] = {}
        # What the worker made of the command being executed (execute_async only).
        self._ready: tuple[_RecipeJob, PreparedRecipe | Exception] | None = None

    # --- the entry ------------------------------------------------------------------------
    def execute(self, command: Command) -> Result:
        """Check, execute and record ``command``; never raises for a refusal."""
        done, tag = command, None
        try:
            if command.verb is Verb.WRITE:
                # A write of a channel's command tag is that command (and is recorded so).
                translated = self._as_channel_command(command)
                if translated is not None:
                    done, tag = translated, str(command.args["tag"])
            result = self._dispatch(done)
        except Refusal as r:
            result = Result.refused(r.kind, r.reason, r.details)
        except Exception as exc:  # a bug: the command is refused and recorded, not lost
            log.exception("command %s on %s failed", command.describe(), command.target)
            result = Result.refused(ResultKind.INTERNAL, f"internal error: {exc}")
        if tag is not None and result.tag is None:
            result = replace(result, tag=tag)
        self._record(done, result)
        return result

    async def execute_async(self, command: Command) -> Result:
        """:meth:`execute` for clients on the running event loop: a recipe to load (``load``,
        ``start`` with a recipe) is read, parsed and compiled in a worker thread while the
        scan goes on, refused past ``compile_timeout_s``; then the command is executed as
        :meth:`execute` does, its checks and the quick install on the loop."""
        job = self._recipe_job(command)
        if job is None:
            return self.execute(command)
        ready: PreparedRecipe | Exception
        busy = self._loading.get(job.channel)
        if busy is not None:
            ready = Refusal(
                ResultKind.REFUSED,
                f"{job.channel}: recipe {busy} is being loaded: wait for its answer",
            )
        else:
            assert self.loader is not None  # _recipe_job saw one
            target = self.loader.target(job.channel)  # a snapshot, taken on the loop
            self._loading[job.channel] = job.recipe
            try:
                folders = None if command.local else self.recipe_folders
                ready = await run_in_worker(
                    lambda: compile_recipe_file(
                        job.channel, job.recipe, target, job.parameters, folders
                    ),
                    self.compile_timeout_s,
                    f"loading {job.recipe} on {job.channel}",
                )
            except WorkerTimeout as exc:
                ready = Refusal(
                    ResultKind.TIMEOUT,
                    f"{job.channel}: recipe refused: reading and compiling {job.recipe} took"
                    f" more than {exc.timeout_s:g} s; the load is abandoned"
                    " (README: Input limits)",
                )
            except Exception as exc:  # refused (ConfigErrors) or a bug: _load tells which
                ready = exc
            finally:
                del self._loading[job.channel]
        self._ready = (job, ready)
        try:
            return self.execute(command)
        finally:
            self._ready = None

    def _recipe_job(self, command: Command) -> _RecipeJob | None:
        """The recipe ``command`` would load, if it passes the checks that need no recipe
        (else None: ``execute`` refuses it with the reason, nothing compiled)."""
        t, a = command.target, command.args
        if t.kind is not TargetKind.CHANNEL or command.verb not in (Verb.LOAD, Verb.START):
            return None
        if self.loader is None or t.name not in self.runners or a.get("recipe") is None:
            return None
        try:
            if self.roles.refuses(command):
                return None
            _only(command, *RECIPE_ARGUMENTS)
            recipe, parameters = _text(a, "recipe"), _parameters(a)
            recipe = self._recipe_file(recipe, command.local)
        except Refusal:
            return None
        return _RecipeJob(t.name, recipe, parameters)

    def _recipe_file(self, recipe: str, local: bool) -> str:
        """The file to open for ``recipe`` (the path policy: ``RecipeFolders``), or
        ``Refusal``: forbidden outside the recipe folders, not found."""
        folders = self.recipe_folders
        if folders is None or local:
            # Not "is a file": a device (/dev/zero) or a pipe is read to its size limit, and
            # refused there with the limit named (README: Input limits).
            if not Path(recipe).exists():
                raise Refusal(ResultKind.NOT_FOUND, f"{recipe}: no such recipe")
            return recipe
        try:
            return str(folders.locate(recipe))
        except RecipeOutside as exc:
            raise Refusal(ResultKind.FORBIDDEN, str(exc)) from None
        except RecipeNotFound as exc:
            raise Refusal(ResultKind.NOT_FOUND, str(exc)) from None

    def _dispatch(self, command: Command) -> Result:
        """Execute ``command`` or raise ``Refusal``."""
        why = self.roles.refuses(command)
        if why:
            raise Refusal(ResultKind.FORBIDDEN, why)
        kind = command.target.kind
        if kind is TargetKind.CHANNEL:
            return self._channel(command)
        if kind is TargetKind.ALARM:
            return self._alarm(command)
        if command.verb not in BENCH_VERBS:
            raise Refusal(ResultKind.NOT_FOUND, f"the bench has no command {command.verb.value}")
        if command.verb in (Verb.FORCE, Verb.UNFORCE):
            return self._force(command)
        if command.verb in ESTOP_VERBS:
            return self._estop(command)
        return self._write(command, command.args)

    # --- channels -----------------------------------------------------------------------
    def _runner(self, c: Command) -> ChainRunner:
        """The channel ``c`` is about, or not found (an unknown channel, a verb no channel has)."""
        name = c.target.name
        runner = self.runners.get(name)
        if runner is None:
            known = ", ".join(self.runners) or "none"
            raise Refusal(ResultKind.NOT_FOUND, f"unknown channel {name!r} (channels: {known})")
        if c.verb not in CHANNEL_VERBS:
            ok = ", ".join(x.value for x in CHANNEL_VERBS)
            raise Refusal(ResultKind.NOT_FOUND, f"a channel has no command {c.verb.value} ({ok})")
        return runner

    def _channel(self, c: Command) -> Result:
        name = c.target.name
        runner = self._runner(c)
        v, a = c.verb, c.args
        if v is Verb.LOAD:
            _only(c, *RECIPE_ARGUMENTS)
            metadata = _metadata(a)
            result = self._load(name, _text(a, "recipe"), _parameters(a), c.local)
            self._set_metadata(name, metadata, replace=True)
            return result
        if v is Verb.START:
            _only(c, *RECIPE_ARGUMENTS)
            return self._start(name, runner, a, c.actor, c.local)
        if v in CHAIN_VERBS:
            _only(c)
            return self._chain(name, runner, v, c.actor)
        if v is Verb.ACKNOWLEDGE:
            _only(c)
            return self._acknowledge(name, runner, c.actor)
        if v is Verb.MODE:
            _only(c, "value", "keep_setpoint")
            mode = _text(a, "value")
            if mode not in (Mode.AUTO.value, Mode.MANUAL.value):
                raise Refusal(
                    ResultKind.BAD_ARGUMENT, f"{name}: mode is auto or manual, not {mode!r}"
                )
            keep = _flag(a, "keep_setpoint", default=False)
            return self._mode(name, runner, mode, keep, c.actor)
        if v is Verb.MANUAL_CURRENT:
            _only(c, "value")
            return self._manual_current(name, runner, _number(a, "value", "A"))
        if v is Verb.ENABLE:
            _only(c, "value")
            return self._enable(name, runner, _flag(a, "value"))
        return self._write(c, a)  # one of this channel's other tags

    def _load(self, name: str, recipe: str, parameters: dict[str, str], local: bool) -> Result:
        loader = self.loader
        if loader is None:
            raise Refusal(ResultKind.NOT_FOUND, NO_LOADER)
        recipe = self._recipe_file(recipe, local)
        job = _RecipeJob(name, recipe, parameters)
        try:
            ready = self._ready[1] if self._ready is not None and self._ready[0] == job else None
            if isinstance(ready, Exception):
                raise ready
            if ready is None:  # no worker: compiled here (no scan is running)
                folders = None if local else self.recipe_folders
                target = loader.target(name)
                ready = compile_recipe_file(name, recipe, target, parameters, folders)
            test_id = loader.install_recipe(ready).test_id
        except ConfigErrors as exc:
            details = tuple(e.location_message() for e in exc.errors)
            raise Refusal(
                ResultKind.INVALID_RECIPE, f"{name}: recipe refused: {details[0]}", details
            ) from None
        except ConfigError as exc:
            msg = exc.location_message()
            raise Refusal(
                ResultKind.INVALID_RECIPE, f"{name}: recipe refused: {msg}", (msg,)
            ) from None
        except OperatorError as exc:
            raise Refusal(ResultKind.REFUSED, str(exc)) from None
        runner = self.runners[name]
        program = runner.program.name if runner.program is not None else ""
        return Result.ok(
            f"{name}: recipe {program} loaded (test {test_id})",
            channel=name,
            test_id=test_id,
            recipe=program,
        )

    def _start(
        self, name: str, runner: ChainRunner, a: Mapping[str, Any], actor: str, local: bool
    ) -> Result:
        # Interlocks and Manual first: a refused start must not load the recipe either.
        self._start_allowed(name, runner)
        metadata = _metadata(a)
        loader = self.loader
        before = loader.test_metadata.get(name) if loader is not None else None
        cell = metadata.get("cell_id", before.cell_id if before is not None else "")
        if cell and loader is not None:
            # One cell is on one channel: a second test of it elsewhere is a wiring or a
            # typing mistake, and two records of one cell at once could not both be right.
            busy = loader.cell_under_test(cell, name)
            if busy is not None:
                raise Refusal(
                    ResultKind.REFUSED,
                    f"{name}: cell {cell!r} is under test on {busy[0]} (test {busy[1]});"
                    " end that test first or give another cell_id",
                )
        loaded = ""
        if a.get("recipe") is not None:
            self._load(name, _text(a, "recipe"), _parameters(a), local)
            self._set_metadata(name, metadata, replace=True)
            loaded = f"recipe {runner.program.name if runner.program else ''} loaded, "
            before = loader.test_metadata.get(name) if loader is not None else None
        was_auto = runner.port.in_auto
        # The test takes its metadata when it starts: set before, put back if refused.
        self._set_metadata(name, {**metadata, "operator": actor}, replace=False)
        try:
            self._run_chain(runner, "start", actor)
        except Refusal:
            if loader is not None:
                loader.test_metadata.pop(name, None)
                if before is not None:
                    loader.test_metadata[name] = before
            raise
        mode = "" if was_auto else " (mode manual → auto)"
        return Result.ok(
            f"{name}: {loaded}test {runner.test_id} started: the step chain drives the "
            f"channel{mode}",
            channel=name,
            test_id=runner.test_id,
            state=runner.state.value,
        )

    def _start_allowed(self, name: str, runner: ChainRunner) -> None:
        """A start's checks that come before its recipe: interlocks, then Manual."""
        self._interlocks(name, runner, "start")
        if runner.port.manual_driven:
            raise Refusal(ResultKind.REFUSED, f"{name}: cannot start while {MANUAL_DRIVEN}")

    def _set_metadata(self, name: str, given: dict[str, Any], replace: bool) -> None:
        if self.loader is not None:
            self.loader.set_test_metadata(name, given, replace)

    def _chain(self, name: str, runner: ChainRunner, verb: Verb, actor: str) -> Result:
        if verb is Verb.RESUME:
            self._interlocks(name, runner, "resume")
        before = runner.state
        self._run_chain(runner, verb.value, actor)
        after = runner.state
        text = f"{name}: {verb.value}: {before.value} → {after.value}"
        if verb is Verb.ADVANCE:
            text = f"{name}: advance: acted on by the next scan"
        elif verb is Verb.RESET:
            text += "; the channel is in manual, enable off, 0 A"
        return Result.ok(text, channel=name, state=after.value)

    @staticmethod
    def _run_chain(runner: ChainRunner, command: str, actor: str) -> None:
        try:
            runner.command(command, actor=actor)
        except OperatorError as exc:
            raise Refusal(ResultKind.REFUSED, str(exc)) from None

    def _acknowledge(self, name: str, runner: ChainRunner, actor: str) -> Result:
        """Acknowledge what holds the channel: the chain's latched alarm, and its trips
        (ISA-18.2: each is reset once acknowledged and its cause gone)."""
        done = _chain_acked(runner)
        if done:
            self._run_chain(runner, "ack", actor)
        guard = self.guards.get(name)
        if guard is not None:
            try:
                reset = guard.reset(actor)
            except OperatorError as exc:
                raise _ack_refused(str(exc), done) from None
            if reset:
                done.append("reset: " + ", ".join(reset))
        return Result.ok(f"{name}: " + ("; ".join(done) or "nothing to acknowledge"))

    def _acknowledge_allowed(self, name: str, runner: ChainRunner) -> None:
        """An acknowledgement is refused (after acknowledging) while a trip's cause is
        present: the guard says so before it is given."""
        guard = self.guards.get(name)
        why = guard.reset_refusal() if guard is not None else ""
        if why:
            raise _ack_refused(why, _chain_acked(runner))

    def _mode(self, name: str, runner: ChainRunner, mode: str, keep: bool, actor: str) -> Result:
        port, db = runner.port, self.db
        if mode == Mode.AUTO.value:
            if port.in_auto:
                return Result.ok(f"{name}: already in auto", tag=port.mode.name)
            self._auto_allowed(name, runner)
            db.update(port.mode, Mode.AUTO.value)
            then = " (Held: resume to continue the test)" if runner.state is State.HELD else ""
            return Result.ok(
                f"{name}: mode auto: the step chain drives the channel{then}", tag=port.mode.name
            )
        if not port.in_auto:
            return Result.ok(f"{name}: already in manual", tag=port.mode.name)
        done: list[str] = []
        if runner.state in RUNNING:
            before = runner.state
            self._run_chain(runner, "hold", actor)  # the chain first: it stops requesting
            done.append(f"chain held (was {before.value})")
        # Bumpless (finding 9): never a setpoint staged earlier. From the present setpoint
        # with the power stage as it was, when asked; else from 0 A, disabled.
        present = port.current_cmd.as_float()
        energised = port.auto_active.value is True and not port.fault_text()
        amps, enable = (present, energised and present != 0.0) if keep else (0.0, False)
        db.update(port.manual_current, amps)
        db.update(port.enable, enable)
        db.update(port.mode, Mode.MANUAL.value)
        done.append(f"manual setpoint {amps:g} A" + (" (kept)" if keep else ""))
        done.append("enable on" if enable else "enable off")
        return Result.ok(f"{name}: mode manual: " + ", ".join(done), tag=port.mode.name)

    @staticmethod
    def _auto_allowed(name: str, runner: ChainRunner) -> None:
        port = runner.port
        if not port.in_auto and port.manual_driven:
            amps = port.manual_current.as_float()
            raise Refusal(
                ResultKind.REFUSED,
                f"{name}: cannot switch to auto while the channel is driven in manual"
                f" (enable on, {amps:g} A): turn enable off first",
            )

    @staticmethod
    def _manual_allowed(name: str, runner: ChainRunner, amps: float | None = None) -> None:
        """A manual setpoint's (or enable's) checks: Manual mode; ``amps`` within the hard
        limits when given."""
        port = runner.port
        if port.in_auto:
            raise Refusal(ResultKind.REFUSED, IN_AUTO.format(ch=name))
        # Beyond the hard limits (the I/O map's limits.current_a, the tag's range): refused,
        # never accepted and silently clamped — an answer must say what will flow.
        hard = port.manual_current.spec.range
        if amps is not None and hard is not None and not hard[0] <= amps <= hard[1]:
            lo, hi = hard
            raise Refusal(
                ResultKind.OUT_OF_RANGE,
                f"{name}: manual setpoint {amps:g} A is beyond the channel's hard limit of"
                f" {hi if amps > hi else lo:g} A (range {lo:g} … {hi:g} A); refused",
            )

    def _manual_current(self, name: str, runner: ChainRunner, amps: float) -> Result:
        port = runner.port
        self._manual_allowed(name, runner, amps)
        self.db.update(port.manual_current, amps)
        off = "" if port.enable.value is True else " (enable is off: nothing flows yet)"
        clamp = self._safety_clamp(name, amps)
        return Result.ok(
            f"{name}: manual setpoint {amps:g} A{clamp}{off}", tag=port.manual_current.name
        )

    def _safety_clamp(self, name: str, amps: float) -> str:
        """What the safety phase's limits of this scan (``chN.limit.charge_a`` /
        ``discharge_a``: a crossed voltage limit, a BMS derating, a trip) make of a setpoint
        inside the hard limits, as the channel will clamp it: "" when it passes whole."""
        which = "charge_a" if amps > 0 else "discharge_a" if amps < 0 else None
        limit = self.db.get(f"{name}.limit.{which}") if which is not None else None
        if limit is None or not isinstance(limit.value, int | float):
            return ""
        allowed = abs(float(limit.value))
        if abs(amps) <= allowed:
            return ""
        flows = math.copysign(allowed, amps)
        return (
            f", clamped to {flows:g} A by the safety limit {limit.name} = {allowed:g} A"
            f" as it stands (shown in {name}.clamped while it clamps)"
        )

    def _enable_allowed(self, name: str, runner: ChainRunner, on: bool) -> None:
        self._manual_allowed(name, runner)
        if on:
            self._interlocks(name, runner, "enable")

    def _enable(self, name: str, runner: ChainRunner, on: bool) -> Result:
        port = runner.port
        self._enable_allowed(name, runner, on)
        self.db.update(port.enable, on)
        amps = port.manual_current.as_float()
        text = f"{name}: enable on at {amps:g} A" if on else f"{name}: enable off"
        return Result.ok(text, tag=port.enable.name)

    def _interlocks(self, name: str, runner: ChainRunner, what: str) -> None:
        """Refuse ``what`` while a trip holds the channel or one of its alarms waits for an
        acknowledgement (the alarm named, and what to do)."""
        alarms = self.alarms
        if alarms is not None:
            for a in alarms.trips(name):
                if a.active:
                    todo = "its cause is still present"
                elif not a.acked:
                    todo = "acknowledge it"
                else:
                    todo = "reset it"
                raise Refusal(
                    ResultKind.REFUSED,
                    f"{name}: {what} refused: tripped by {a.id} ({a.message}): {todo}",
                )
            for a in alarms.in_alarm(name):
                if not a.acked:
                    raise Refusal(
                        ResultKind.REFUSED,
                        f"{name}: {what} refused: alarm {a.id} is unacknowledged ({a.message})",
                    )
        fault = runner.port.fault_text()
        if fault:
            raise Refusal(ResultKind.REFUSED, f"{name}: {what} refused: channel fault ({fault})")
        alarm = runner.situation().alarm
        if what == "start" and alarm is not None:
            raise Refusal(
                ResultKind.REFUSED, f"{name}: start refused: acknowledge the alarm first ({alarm})"
            )

    # --- alarms -------------------------------------------------------------------------
    def _alarm(self, c: Command) -> Result:
        alarm_id = c.target.name
        alarms = self.alarms
        if alarms is None or alarm_id not in alarms:
            raise Refusal(ResultKind.NOT_FOUND, f"unknown alarm {alarm_id!r}")
        v = c.verb
        if v not in ALARM_VERBS:
            ok = ", ".join(x.value for x in ALARM_VERBS)
            raise Refusal(ResultKind.NOT_FOUND, f"an alarm has no command {v.value} ({ok})")
        try:
            if v is Verb.SHELVE:
                _only(c, "duration_s")
                alarm = alarms.shelve(alarm_id, _number(c.args, "duration_s", "s"), c.actor)
            else:
                _only(c)
                if v is Verb.ACKNOWLEDGE:
                    alarm = alarms.acknowledge(alarm_id, c.actor)
                elif v is Verb.RESET:
                    alarm = alarms.reset(alarm_id, c.actor)
                else:
                    alarm = alarms.unshelve(alarm_id, c.actor)
        except OperatorError as exc:
            raise Refusal(ResultKind.REFUSED, str(exc)) from None
        return Result.ok(f"alarm {alarm_id} {v.value}: now {alarm.state.value}", alarm=alarm_id)

    # --- tags ---------------------------------------------------------------------------
    def _as_channel_command(self, c: Command) -> Command | None:
        """A write of ``chN.command|mode|manual_current|enable|ack`` as the channel command
        it is (so it takes that command's checks); None for any other tag."""
        _only(c, "tag", "value")
        name = _text(c.args, "tag")
        t = c.target
        if t.kind is TargetKind.CHANNEL and not name.startswith(f"{t.name}."):
            raise Refusal(ResultKind.BAD_ARGUMENT, f"{name} is not a tag of channel {t.name}")
        if "value" not in c.args:
            raise Refusal(ResultKind.BAD_ARGUMENT, f"{name}: no value to write")
        value = c.args["value"]
        channel, _, field = name.partition(".")
        if channel not in self.runners or field not in CHANNEL_COMMAND_TAGS:
            return None
        if field == "command":
            verb = Verb.parse(value) if isinstance(value, str) else None
            if verb is None or verb not in (*CHAIN_VERBS, Verb.ACKNOWLEDGE):
                ok = ", ".join([*(x.value for x in CHAIN_VERBS), "ack"])
                raise Refusal(
                    ResultKind.BAD_ARGUMENT, f"{name}: unknown command {clipped_repr(value)} ({ok})"
                )
            return Command.channel(channel, verb, c.actor)
        if field == "ack":
            if _flag(c.args, "value") is not True:
                raise Refusal(ResultKind.BAD_ARGUMENT, f"write true to {name} to acknowledge")
            return Command.channel(channel, Verb.ACKNOWLEDGE, c.actor)
        verb = {"mode": Verb.MODE, "manual_current": Verb.MANUAL_CURRENT, "enable": Verb.ENABLE}[
            field
        ]
        return Command.channel(channel, verb, c.actor, value=value)

    def _write(self, c: Command, a: Mapping[str, Any]) -> Result:
        _only(c, "tag", "value")
        name = _text(a, "tag")
        tag = self.db.get(name)
        if tag is None:
            raise Refusal(ResultKind.NOT_FOUND, f"unknown tag {name!r}")
        if "value" not in a:
            raise Refusal(ResultKind.BAD_ARGUMENT, f"{name}: no value to write")
        spec = tag.spec
        if spec.access is Access.READ_ONLY:
            raise Refusal(ResultKind.FORBIDDEN, f"{name} is read-only")
        access = self.roles.access_of(c.actor)
        if access < spec.access:
            raise Refusal(ResultKind.FORBIDDEN, f"{name} needs {spec.access.name.lower()} access")
        try:
            value = spec.coerce(a["value"])
        except (TypeError, ValueError) as exc:
            raise Refusal(ResultKind.BAD_ARGUMENT, str(exc)) from None
        try:
            self.db.write(name, value, access)
        except OperatorError as exc:  # a choice or a range: the value is wrong
            raise Refusal(ResultKind.BAD_ARGUMENT, str(exc)) from None
        return Result.ok(f"{name} := {tag.value!r}", tag=name)

    def _force(self, c: Command) -> Result:
        """Force or unforce a tag: engineers only, never a tag the safety phase reads or
        drives (a force must never defeat the e-stop or a channel's guard), nor a channel's
        command tag (give the command instead: it takes the command's checks)."""
        forcing = c.verb is Verb.FORCE
        if forcing:
            _only(c, "tag", "value")
        else:
            _only(c, "tag")
        name = _text(c.args, "tag")
        self._force_allowed(c, name)
        tag = self.db.get(name)
        if tag is None:
            raise Refusal(ResultKind.NOT_FOUND, f"unknown tag {name!r}")
        if not forcing:
            if not tag.forced:
                return Result.ok(f"{name} was not forced", tag=name)
            self.db.unforce(name)
            return Result.ok(
                f"{name} unforced: last known value until the process writes it", tag=name
            )
        why = self.protected.get(name)
        if why is not None:
            raise Refusal(
                ResultKind.REFUSED,
                f"{name} cannot be forced: {why} (a force never overrides the safety phase)",
            )
        channel, _, field = name.partition(".")
        if channel in self.runners and field in CHANNEL_COMMAND_TAGS:
            raise Refusal(
                ResultKind.REFUSED,
                f"{name} cannot be forced: a command tag of {channel} (give the command)",
            )
        if "value" not in c.args:
            raise Refusal(ResultKind.BAD_ARGUMENT, f"{name}: no value to force")
        spec = tag.spec
        try:
            value = parse_forced(spec, c.args["value"])
        except (TypeError, ValueError) as exc:
            raise Refusal(ResultKind.BAD_ARGUMENT, str(exc)) from None
        if spec.choices is not None and value not in spec.choices:
            choices = ", ".join(spec.choices)
            raise Refusal(ResultKind.BAD_ARGUMENT, f"{name}: {value!r} is not one of {choices}")
        rng = spec.range
        if rng is not None and isinstance(value, int | float) and not isinstance(value, bool):
            lo, hi = rng
            if not lo <= value <= hi:
                raise Refusal(
                    ResultKind.BAD_ARGUMENT,
                    f"{name}: {value} {spec.unit} is outside its range [{lo}, {hi}]".strip(),
                )
        self.db.force(name, value)
        return Result.ok(f"{name} forced := {value!r} (until unforced)", tag=name)

    def _force_allowed(self, c: Command, name: str) -> None:
        if self.roles.access_of(c.actor) < Access.ENGINEER:
            what = f"{c.verb.value} {name}" if name else c.verb.value
            raise Refusal(ResultKind.FORBIDDEN, f"{what}: needs engineer access")

    # --- the software e-stop -------------------------------------------------------------
    def _estop(self, c: Command) -> Result:
        """Press or reset the bench-wide software e-stop (operators; a viewer is refused
        by the role hook before this). A press is never refused for the bench's state: a
        second one is accepted and says who pressed first. A reset takes the hardware
        e-stop's rule: refused while unacknowledged or while the button is pressed."""
        _only(c)
        what = "press the e-stop" if c.verb is Verb.ESTOP else "reset the e-stop"
        if self.roles.access_of(c.actor) < Access.OPERATOR:
            raise Refusal(ResultKind.FORBIDDEN, f"{c.actor} may not {what}: needs operator access")
        estop = self.estop
        if estop is None:
            raise Refusal(
                ResultKind.NOT_FOUND,
                "this bench has no e-stop (safety.estop in its I/O map): abort each channel",
            )
        if c.verb is Verb.ESTOP:
            return Result.ok(estop.press(c.actor), alarm=estop.alarm.id)
        try:
            reason = estop.release(c.actor)
        except OperatorError as exc:
            raise Refusal(ResultKind.REFUSED, str(exc)) from None
        return Result.ok(reason, alarm=estop.alarm.id)

    # --- what would be accepted now (issue 33: a screen's buttons follow the state) --------
    def check(self, command: Command) -> Result:
        """What :meth:`execute` would answer ``command`` now, without executing or recording
        it: refused with the kind and reason ``execute`` would give, or accepted ("would be
        accepted"). The checks are ``execute``'s own, in its order — role, target, the
        state table, Auto/Manual, interlocks; an argument not given is not checked (a
        recipe's file, a setpoint: known once the operator gives them), nor a start's cell.
        A channel's commands, and force's role (ValueError for any other command)."""
        try:
            why = self.roles.refuses(command)
            if why:
                raise Refusal(ResultKind.FORBIDDEN, why)
            t, v = command.target, command.verb
            if t.kind is TargetKind.BENCH and v in (Verb.FORCE, Verb.UNFORCE):
                self._force_allowed(command, str(command.args.get("tag") or ""))
            elif t.kind is TargetKind.CHANNEL and v is not Verb.WRITE:
                self._channel_allowed(command)
            else:
                raise ValueError(f"{command.describe()} on {t} is not checked ahead")
        except Refusal as r:
            return Result.refused(r.kind, r.reason, r.details)
        return Result.ok(f"{command.target}: {command.describe()} would be accepted")

    def available(self, channel: str, actor: str) -> dict[str, Result]:
        """A channel's command bar (``CHANNEL_BAR``, and ``force``) as :meth:`check`
        answers each of its commands for ``actor`` now."""
        out = {
            key: self.check(Command(Target.channel(channel), verb, dict(args), actor))
            for key, verb, args in CHANNEL_BAR
        }
        out["force"] = self.check(Command(Target.bench(), Verb.FORCE, {}, actor))
        return out

    def _channel_allowed(self, c: Command) -> None:
        """``check`` of a channel command: the checks each handler makes before it acts."""
        runner = self._runner(c)
        name, v, a = c.target.name, c.verb, c.args
        if v is Verb.LOAD:
            if self.loader is None:
                raise Refusal(ResultKind.NOT_FOUND, NO_LOADER)
            _decided(check_load, name, runner.state, runner.port.manual_driven)
        elif v in CHAIN_VERBS:
            if v is Verb.START:
                self._start_allowed(name, runner)
            elif v is Verb.RESUME:
                self._interlocks(name, runner, "resume")
            _decided(decide, name, runner.state, v.value, runner.situation())
        elif v is Verb.ACKNOWLEDGE:
            self._acknowledge_allowed(name, runner)
        elif v is Verb.MODE:
            if a.get("value") == Mode.AUTO.value:
                self._auto_allowed(name, runner)
        elif v is Verb.MANUAL_CURRENT:
            amps = _number(a, "value", "A") if "value" in a else None
            self._manual_allowed(name, runner, amps)
        elif v is Verb.ENABLE:
            self._enable_allowed(name, runner, _flag(a, "value"))

    # --- the record -----------------------------------------------------------------------
    def _record(self, c: Command, result: Result) -> None:
        now = self.clock.now()
        channel = self._channel_of(c)
        ev = CommandEvent(
            now,
            self.clock.to_wall(now),
            c.actor,
            str(c.target),
            c.describe(),
            result.accepted,
            result.kind,
            result.reason,
            channel,
        )
        self.log.append(ev)
        level = logging.INFO if result.accepted else logging.WARNING
        log.log(level, "command on %s: %s", ev.target, ev.text)
        # A bench-wide e-stop goes into every channel's timeline (their result files).
        names = list(self.runners) if c.verb in ESTOP_VERBS else [channel]
        for name in names:
            runner = self.runners.get(name)
            if runner is None:
                continue
            try:
                runner.record_command(ev.text)
            except Exception:
                log.exception("%s: recording a command failed", name)
        for fn in self.listeners:
            try:
                fn(ev)
            except Exception:
                log.exception("command listener failed")
        if self.audit is not None:  # queued: never waits for the disk, never raises
            self.audit.append(c.actor, f"command.{c.verb.value}", ev.target, _audited(c, ev))

    def _channel_of(self, c: Command) -> str:
        t = c.target
        if t.kind is TargetKind.CHANNEL:
            return t.name if t.name in self.runners else ""
        if t.kind is TargetKind.ALARM:
            alarms = self.alarms
            if alarms is not None and t.name in alarms and alarms[t.name].group in self.runners:
                return alarms[t.name].group
            return ""
        tag = c.args.get("tag")
        channel = tag.partition(".")[0] if isinstance(tag, str) else ""
        return channel if channel in self.runners else ""


def _audited(c: Command, ev: CommandEvent) -> dict[str, Any]:
    """What the audit trail keeps of a command: as given (its arguments) and as answered."""
    return {
        "command": ev.command,
        "args": dict(c.args),
        "accepted": ev.accepted,
        "result": ev.kind.value,
        "reason": ev.reason,
        "channel": ev.channel,
    }


@dataclass(frozen=True)
class _RecipeJob:
    """A recipe to load on a channel, as a command asks for it."""

    channel: str
    recipe: str
    parameters: Mapping[str, str]


def _chain_acked(runner: ChainRunner) -> list[str]:
    """What an acknowledgement of the channel does to its chain (its latched alarm)."""
    alarm = runner.situation().alarm
    return [f"chain alarm acknowledged ({alarm})"] if alarm is not None else []


def _ack_refused(why: str, done: list[str]) -> Refusal:
    also = f" ({'; '.join(done)})" if done else ""
    return Refusal(ResultKind.REFUSED, f"{why}; acknowledged{also}: reset once the cause is gone")


def _decided(rule: Callable[..., object], *args: Any) -> None:
    """A rule of the state table (``decide``, ``check_load``) as a check: its
    ``OperatorError`` is a refusal with its words."""
    try:
        rule(*args)
    except OperatorError as exc:
        raise Refusal(ResultKind.REFUSED, str(exc)) from None


# --- arguments ------------------------------------------------------------------------------
def _metadata(a: Mapping[str, Any]) -> dict[str, Any]:
    """The test metadata among a load's or a start's arguments, checked."""
    try:
        return metadata_from_arguments(a)
    except MetadataError as exc:
        raise Refusal(ResultKind.BAD_ARGUMENT, str(exc)) from None


def _only(c: Command, *allowed: str) -> None:
    """Unknown arguments are errors (STYLE.md: never silently drop an entry)."""
    unknown = sorted(set(c.args) - set(allowed))
    if unknown:
        expected = ", ".join(allowed) or "none"
        raise Refusal(
            ResultKind.BAD_ARGUMENT,
            f"{c.verb.value}: unknown argument {', '.join(unknown)} (expected: {expected})",
        )


def _text(a: Mapping[str, Any], key: str) -> str:
    x = a.get(key)
    if not isinstance(x, str) or not x:
        raise Refusal(ResultKind.BAD_ARGUMENT, f"{key} must be a text, not {clipped_repr(x)}")
    return x


def _number(a: Mapping[str, Any], key: str, unit: str) -> float:
    """A finite number (a boolean is not one; nor NaN, ±inf, or 1 followed by 400 zeros)."""
    x = a.get(key)
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise Refusal(
            ResultKind.BAD_ARGUMENT, f"{key} must be a number ({unit}), not {clipped_repr(x)}"
        )
    number = finite_float(x)
    if number is None:
        raise Refusal(
            ResultKind.BAD_ARGUMENT,
            f"{key} must be a number ({unit}), a finite one, not {clipped_repr(x)}",
        )
    return number


_TRUE = ("true", "on", "yes", "1")
_FALSE = ("false", "off", "no", "0")


def _flag(a: Mapping[str, Any], key: str, default: bool | None = None) -> bool:
    x = a.get(key, default)
    if isinstance(x, bool):
        return x
    if isinstance(x, str) and x.strip().lower() in (*_TRUE, *_FALSE):
        return x.strip().lower() in _TRUE
    raise Refusal(ResultKind.BAD_ARGUMENT, f"{key} must be true or false, not {clipped_repr(x)}")


def _parameters(a: Mapping[str, Any]) -> dict[str, str]:
    p = a.get("parameters") or {}
    if not isinstance(p, Mapping):
        raise Refusal(
            ResultKind.BAD_ARGUMENT, f"parameters must be a mapping, not {clipped_repr(p)}"
        )
    out: dict[str, str] = {}
    for k, v in p.items():
        # A quantity as text ("1.8 V") or a finite number; never a boolean (not 1 V).
        number = isinstance(v, int | float) and not isinstance(v, bool)
        if not isinstance(k, str) or not (isinstance(v, str) or number):
            raise Refusal(
                ResultKind.BAD_ARGUMENT,
                f"parameter {clipped_repr(k)}: {clipped_repr(v)} is not a value"
                " (a quantity such as '1.8 V')",
            )
        if number and finite_float(v) is None:
            raise Refusal(
                ResultKind.BAD_ARGUMENT, f"parameter {k}: {clipped_repr(v)} is not a finite number"
            )
        out[k] = str(v)
    return out
