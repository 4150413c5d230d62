"""A supervisor, whole: a bench with its HTTP API, operator screens and OPC UA server.

What ``supervisor run`` serves, built here and not in the command line (issue 29, finding
6), so that embedding a supervisor is one call::

    async with serve(load_bench("io_maps/sim.yaml")) as sup:
        ...  # sup.api.url, sup.bench.db, sup.opcua; leaving stops it, outputs safe

The command line parses its arguments, sets logging, says what listens where and
handles the signals; it calls ``build_supervisor``, ``Supervisor.load``, ``start`` and
``run`` itself only because it reports between them.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final

from supervisor.app.audit import open_audit
from supervisor.app.bench import Bench, build_bench
from supervisor.app.descriptors import http_limits
from supervisor.app.hmi import build_screens
from supervisor.app.lock import BenchLock, BenchLockFailed
from supervisor.app.notify import build_notifier
from supervisor.app.preview import previews_of
from supervisor.app.sparkplug import screens_url
from supervisor.commands import Command, Result, Verb
from supervisor.config.models import BenchConfig
from supervisor.core.clock import Clock, RealClock
from supervisor.core.heap import collect_when_idle, settle_after_start
from supervisor.hmi import HttpApi
from supervisor.hmi.auth import session_actor, session_role
from supervisor.hmi.recipes_api import RecipesConfig, recipe_checks
from supervisor.hmi.screens import Screens
from supervisor.hmi.tests_api import TestsConfig

if TYPE_CHECKING:
    from supervisor.notify import Notifier
    from supervisor.publish.modbus.server import ModbusServer
    from supervisor.publish.opcua import OpcUaProcess, OpcUaServer

log = logging.getLogger(__name__)

START_WAIT_S: Final = 10.0
"""``supervisor run --start``: how long a test waits for its channel's inputs to read GOOD
after the scan began, before its start is refused."""

START_POLL_S: Final = 0.05
"""How often ``start_when_ready`` looks at the channels still waiting."""

ACTOR: Final = "command line"
"""Who loads and starts the recipes given to ``build_supervisor``'s caller (the shell)."""


@dataclass
class Supervisor:
    """A bench and the servers around it, built (``build_supervisor``), then ``start``,
    ``run`` until a stop, and ``release``. ``serve`` does it all in one call."""

    bench: Bench
    api: HttpApi
    screens: Screens
    opcua: OpcUaServer | OpcUaProcess | None
    """On a real clock, in a process of its own (ADR 0029)."""
    recipes: RecipesConfig
    restored: list[str]
    """What the restore of the retained state did or could not do, one line each."""
    lock: BenchLock | None = None
    unconfirmed: dict[str, str] | None = None
    """After ``run``: the devices that could not confirm their safe state, each with why."""
    _starter: asyncio.Task[None] | None = field(default=None, repr=False)
    modbus: ModbusServer | None = None
    """When the I/O map has a ``modbus_server:`` section (app/modbus.py, ADR 0032)."""
    notifier: Notifier | None = None
    """When the I/O map has a ``notifications:`` section (app/notify.py)."""

    async def load(
        self, channel: str, recipe: str, parameters: dict[str, str] | None = None
    ) -> Result:
        """Load ``recipe`` (the shell's own file: not confined to the recipe folders, ADR
        0026) on ``channel`` through the command path, as the HTTP API would: checked,
        compiled in a worker thread with its time limit, and recorded."""
        load = Command.channel(
            channel, Verb.LOAD, ACTOR, recipe=recipe, parameters=parameters or {}
        )
        return await self.bench.commands.execute_async(dataclasses.replace(load, local=True))

    async def start(self) -> None:
        """Listen (HTTP API, OPC UA, Modbus TCP) and start the bench's simulators and writers.
        An ``OSError`` (a port taken) stops what had started before it is raised."""
        opcua, modbus, api, bench = self.opcua, self.modbus, self.api, self.bench
        try:
            await api.start()
            if self.recipes.checks is not None:
                self.recipes.checks.warm()
            if opcua is not None:
                await opcua.start()
            if modbus is not None:
                await modbus.start()
            if bench.sparkplug is not None:  # the fleet's link to this bench's screens
                bench.sparkplug.hmi_url = screens_url(api.host, api.port)
            await bench.start()
            if self.notifier is not None:
                await self.notifier.start()  # the queue left by the last run is sent first
        except OSError:
            await bench.shutdown()
            if modbus is not None:
                await modbus.stop()
            if opcua is not None:
                await opcua.stop()
            await api.stop()
            raise

    async def run(self, stop: asyncio.Event, start: Sequence[str] = ()) -> dict[str, str]:
        """Scan until ``stop`` is set, then every output to its safe state and the servers
        stopped. ``start``: channels whose loaded test starts once their inputs read GOOD
        (``start_when_ready``). Returns the devices that could not confirm their safe
        state, each with why (empty: all safe)."""
        bench = self.bench
        # Start-up is over: what it built lives as long as the process (ADR 0018). Left in
        # the collector's generations, the first full collections after start-up — set off
        # by the first page's allocations — walked it all on the scan's thread (60–130 ms;
        # the 0.46 s scan.stall of the browser tests on a busy machine; ADR 0019).
        settle_after_start()
        bench.engine.idle = collect_when_idle  # the collector's turn between scans (ADR 0021)
        if start:
            self._starter = asyncio.create_task(start_when_ready(bench, list(start)))
        try:
            await bench.run(stop)
        finally:
            unconfirmed = await self._stop()
        return unconfirmed

    async def _stop(self) -> dict[str, str]:
        bench, opcua = self.bench, self.opcua
        if self.recipes.checks is not None:
            self.recipes.checks.kill_all()  # a check under way is abandoned at once (issue 28)
        if self._starter is not None:
            self._starter.cancel()
            await asyncio.gather(self._starter, return_exceptions=True)
            self._starter = None
        if opcua is not None:
            opcua.closing()  # no command while the outputs go safe; clients see them go
        if self.modbus is not None:
            self.modbus.closing()
        unconfirmed = await bench.shutdown()
        if self.notifier is not None:
            # After the outputs are safe: the stop's own alarms are queued, not lost.
            await self.notifier.stop()
        if opcua is not None:
            await opcua.stop()
        if self.modbus is not None:
            await self.modbus.stop()
        await self.api.stop()
        if bench.sim is not None:
            bench.sim.release()  # the process ends
        if self.recipes.checks is not None:
            # Killed above; now reaped: an embedding process goes on after the stop, and a
            # killed check's pipes left to the collector are an unclosed transport there.
            await self.recipes.checks.close()
        self.unconfirmed = unconfirmed
        return unconfirmed

    def release(self) -> None:
        """After ``run`` (or instead of it, e.g. a refused recipe): the retained state's
        store closed if the bench never ran, and the bench's lock dropped."""
        if self.bench.retention is not None:  # left before the bench ran
            self.bench.retention.close()
            self.bench.retention = None
        if self.bench.audit is not None:  # likewise
            self.bench.audit.close()
            self.bench.audit = None
        if self.lock is not None:
            self.lock.release()


def build_supervisor(
    cfg: BenchConfig,
    clock: Clock | None = None,
    *,
    simulate: bool = True,
    http_port: int | None = None,
    display_period_s: float = 60.0,
    lock: bool = True,
) -> Supervisor:
    """Build the supervisor of ``cfg`` (nothing listens or runs yet: ``start``).

    One bench, one supervisor (docs/adr/0010-retained-state.md): with ``lock`` the bench's
    lock is taken before anything touches a device, a simulator or a port (``BenchBusy``
    names its holder, ``BenchLockFailed`` says why it could not be taken). Then the bench
    (``simulate=False``: another process serves its simulators), its retained state
    restored (a test that was under way comes back Held), its history recorded, the HTTP
    API on ``http_port`` (None: the I/O map's), the screens and, when the I/O map enables
    it, OPC UA. ``ConfigError`` for a bad users file. ``display_period_s``: how often the
    Chadèche boards' displays are rewritten."""
    held = BenchLock(cfg.state_dir, cfg.bench) if lock else None
    if held is not None:
        try:
            held.acquire()
        except OSError as exc:
            raise BenchLockFailed(held.path, exc) from exc
    bench: Bench | None = None
    try:
        bench = build_bench(cfg, clock or RealClock(), simulate=simulate)
        # Its notify.* tags and alarm exist before the history, the retained state and
        # the servers list the bench's tags and alarms.
        notifier = build_notifier(bench)
        bench.audit = open_audit(bench)  # before any command: the I/O map's load first
        restored = bench.retain()
        bench.record_history()
        sup = _serve_bench(cfg, bench, restored, http_port)
        sup.notifier = notifier
    except BaseException:
        if bench is not None and bench.retention is not None:
            bench.retention.close()
            bench.retention = None
        if bench is not None and bench.audit is not None:
            bench.audit.close()
            bench.audit = None
        if held is not None:
            held.release()
        raise
    sup.lock = held
    for display in bench.displays.values():
        display.period_s = display_period_s
    return sup


def _serve_bench(
    cfg: BenchConfig, bench: Bench, restored: list[str], http_port: int | None
) -> Supervisor:
    # The e-stop button presses the simulated plant's e-stop (seed 002 bench only).
    estop = bench.sim.press_estop if bench.sim is not None and bench.sim.served else None
    history = bench.historian.query if bench.historian is not None else None
    recipes = _recipes_config(cfg, bench)
    api = HttpApi(
        bench.db,
        bench.clock,
        cfg.hmi.host,
        cfg.hmi.port if http_port is None else http_port,
        estop=estop,
        commands=bench.commands,
        history=history,
        recipes=recipes,
        tests=TestsConfig(Path(cfg.state_dir) / "results", bench.results, bench.runners),
        pacing=bench.engine,
        allowed_origins=cfg.hmi.allowed_origins,
        limits=http_limits(cfg),
    )
    screens = build_screens(bench, api)  # ConfigError for a bad users file
    opcua = None
    if cfg.opcua.enabled:
        from supervisor.app.opcua import build_opcua

        # On a real clock the server runs in a process of its own: its clients cost the scan
        # neither the interpreter lock nor turns of its loop (ADR 0029). A virtual clock's
        # bench has no real time to protect, and its tests step the server with the scan.
        opcua = build_opcua(bench, process=not bench.clock.virtual)  # ConfigError: users file
    modbus = None
    if cfg.modbus_server is not None:
        from supervisor.app.modbus import build_modbus

        modbus = build_modbus(bench)
    return Supervisor(bench, api, screens, opcua, recipes, restored, modbus=modbus)


def _recipes_config(cfg: BenchConfig, bench: Bench) -> RecipesConfig:
    """The HMI's recipes: the recipe folders the command path loads from; its dry-run
    preview in a child process (app/preview.py)."""
    # The command path's folders (one path policy, ADR 0026); the editor saves into the
    # first. A save needs an engineer's session: the same users and roles as the commands.
    folders = bench.commands.recipe_folders
    assert folders is not None  # a bench always has its I/O map's
    # Recipe texts from the network are checked in child processes, killed when abandoned
    # (issue 28); started now so that the first check does not wait for their imports.
    checks = recipe_checks(cfg.recipes.check_workers, cfg.recipes.check_memory_mib * 1024 * 1024)
    return RecipesConfig(
        folders.folders[0],
        previews_of(cfg),
        validate_timeout_s=cfg.recipes.check_timeout_s,
        checks=checks,
        folders=folders,
        target_of=bench.target,
        channels=bench.runners,
        role_of=session_role,
        actor_of=session_actor,
        audit=bench.audit,  # recipe saves: their content's SHA-256 and diff
    )


@contextlib.asynccontextmanager
async def serve(
    cfg: BenchConfig,
    clock: Clock | None = None,
    *,
    simulate: bool = True,
    http_port: int | None = None,
    lock: bool = True,
) -> AsyncIterator[Supervisor]:
    """A supervisor of ``cfg`` built, listening and scanning for the block's duration;
    leaving the block stops it (every output safe) and releases the bench. A device that
    could not confirm its safe state is logged (``Bench.shutdown``)."""
    sup = build_supervisor(cfg, clock, simulate=simulate, http_port=http_port, lock=lock)
    try:
        await sup.start()
        stop = asyncio.Event()
        running = asyncio.create_task(sup.run(stop), name=f"supervisor {cfg.bench}")
        try:
            yield sup
        finally:
            stop.set()
            await running
    finally:
        sup.release()


async def start_when_ready(bench: Bench, channels: list[str]) -> None:
    """``--start``: each loaded test started once the inputs its channel's guard checks read
    GOOD (``ChannelGuard.inputs_not_good``). Started at the first scan, a test whose BMS
    had not sent its first frames yet tripped its channel at once (Held, with the alarm "BMS
    value … is BAD (initial value)") on a busy machine. A channel still waiting after
    ``START_WAIT_S`` is not started: its start is refused in the log, with what it waited
    for; the operator starts it when the bench is ready."""
    guards = bench.safety.guards
    deadline = time.monotonic() + START_WAIT_S
    waiting = list(channels)
    while waiting:
        late = time.monotonic() >= deadline
        for ch in list(waiting):
            guard = guards.get(ch)
            missing = guard.inputs_not_good() if guard is not None else []
            if missing and not late:
                continue
            waiting.remove(ch)
            if missing:
                log.error(
                    "--start %s: start refused: its inputs do not read GOOD %g s after the"
                    " scan began: %s",
                    ch,
                    START_WAIT_S,
                    ", ".join(missing),
                )
                continue
            result = await bench.commands.execute_async(Command.channel(ch, Verb.START, ACTOR))
            if not result.accepted:
                log.error("--start %s: start refused: %s", ch, result.reason)
        if waiting:
            await asyncio.sleep(START_POLL_S)
