"""EA-PSB 10000 simulator: the EA SCPI subset over the plant, in process or served on TCP.

:class:`EaSimulator` is the unit: its SCPI interpreter (:meth:`EaSimulator.handle_line`), its
state and the test hooks. It has no socket and no task of its own, so a driver can talk to
it in process (:class:`~supervisor.fieldbus.scpi_transport.InProcessScpiTransport`) on a
virtual clock. :class:`EaTcpSimulator` is the same unit served on loopback for drivers in
another process or on real TCP.

The simulated unit drives :class:`~supervisor.sim.plant.BenchPlant` (its ``supply`` settings);
the plant decides the current. Behaviour modelled (devices.md "EA-PSB 10000"):

* settings and ``OUTP ON`` need remote control (``SYST:LOCK ON``), else ``-201`` is queued;
  values above the nominal ratings (or negative) queue ``-222``; unknown commands ``-100``;
* several commands per line with ``;``, replies joined with ``;`` on one line;
* protections: measured V above ``VOLT:PROT``, |I| above ``CURR:PROT``/``SINK:CURR:PROT`` or
  |P| above ``POW:PROT`` switch the output off and latch a ``STAT:QUES:COND?`` bit (OVP 0,
  OCP 1, OPP 2) until ``SYST:ERR?`` or ``*CLS`` acknowledges it;
* interface monitoring: after ``SYST:COMM:MON:ACT ON``, no command line for ``TIM`` seconds
  makes the unit leave remote and switch the output off (``POW:STAG:AFT:REM OFF``). A client
  that disconnects does NOT by itself switch anything off.

When the watchdog and the protections are enforced:

* in process (:class:`EaSimulator`), lazily: before every command line (a line arriving
  after the timeout finds the unit already out of remote with its output off, as a real
  unit would have switched off in between), after every line that is not only queries
  (a setting may trip a protection at once), and whenever
  :meth:`EaSimulator.check` is called — a test that lets virtual time pass without a line
  calls it to see what the unit did meanwhile. Nothing sleeps, so virtual time only moves
  with the scan. A protection crossed between two lines acts when the next one arrives
  (the plant integrates the current that flowed until then): at most one poll late;
* served (:class:`EaTcpSimulator`), also by a checker task every ``CHECK_PERIOD_S`` on the
  plant's clock, so they act between commands; use a real clock (a virtual clock would be
  advanced by the checker's own sleeps).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable

from supervisor.core.errors import ProtocolError
from supervisor.devices.ea.protocol import (
    OPER_CC_BIT,
    OPER_CV_BIT,
    OPER_SINK_BIT,
    QUES_OCP_BIT,
    QUES_OPP_BIT,
    QUES_OVP_BIT,
    WATCHDOG_ENABLE_HEADER,
    WATCHDOG_TIME_HEADER,
    LockOwner,
    Measurement,
    format_meas_array,
    parse_command,
)
from supervisor.fieldbus.scpi import (
    ERR_COMMAND,
    ERR_DATA_OUT_OF_RANGE,
    ERR_INVALID_IN_LOCAL,
    ERR_NONE,
    ERR_PARAMETER,
    ERROR_MESSAGES,
    MAX_LINE_BYTES,
    REPLY_SEPARATOR,
    STB_ERROR_QUEUE_BIT,
    STB_QUES_BIT,
    Command,
    Identity,
    decode_line,
    format_error,
    format_idn,
    parse_number,
    parse_on_off,
    split_commands,
)
from supervisor.sim.plant import BenchPlant

log = logging.getLogger(__name__)

CHECK_PERIOD_S = 0.02
"""How often the checker enforces protections and the watchdog."""
ERROR_QUEUE_LENGTH = 20
DEFAULT_PROTECTION_FRACTION = 1.1
"""Protections power up at 110 % of nominal (EA default [S]); settable up to nominal here."""
SIM_SERIAL = "2775129999"
SIM_FIRMWARE = "V3.03 05.10.2022 V3.06 24.05.2023 V1.0.2.20"
_CC_TOLERANCE_A = 1e-3
PARSE_CACHE_SIZE = 256
LINE_LOG_LENGTH = 4096
"""How many received lines (and commands) the simulator keeps for tests to look at.

Bounded: a bench simulated for days receives a line per poll, and an unbounded log grew by
about 7 MiB per hour (issue 13). The newest are kept; the oldest go in blocks of half the
length so that trimming costs O(1) per line on average."""
"""Command texts whose parse the simulator remembers (see ``EaSimulator._parse``)."""

RATING_DECIMALS = 2
"""Decimals of the simulated unit's ``SYST:NOM:…?`` replies (``60.00 V``)."""

_Handler = Callable[[Command], str | None]


def reported_rating(value: float) -> float:
    """A rating as the unit reports it (:data:`RATING_DECIMALS`): the value it enforces."""
    return float(f"{value:.{RATING_DECIMALS}f}")


class _Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class _Session:
    """One in-process client connection; the unit closes it in ``drop_clients()``."""

    __slots__ = ("_unit", "open")

    def __init__(self, unit: EaSimulator) -> None:
        self._unit = unit
        self.open = True

    def close(self) -> None:
        self.open = False
        self._unit._sessions.discard(self)


class EaSimulator:
    """One simulated EA unit: SCPI interpreter and state, no socket, no task.

    Its network link starts plugged in: in-process clients connect with
    :meth:`open_session`. :meth:`stop` unplugs it (sessions dropped, new ones refused, the
    unit keeps its state: unplugged from the network, not from mains); :meth:`start` plugs
    it in again. Nothing is served: :meth:`addresses` is empty.

    Test hooks: ``commands`` (every command received, in order), ``lines`` (every command
    line), :meth:`drop_clients`, :meth:`set_local`, :meth:`corrupt_next_reply`,
    :meth:`queue_error`, ``mute`` (stop answering queries), ``watchdog_trips``,
    ``protection_trips``, :meth:`check`.
    """

    def __init__(
        self,
        plant: BenchPlant,
        model: str = "PSB 10060-60",
        nominal_v: float = 60.0,
        nominal_a: float = 60.0,
        nominal_w: float = 1500.0,
        name: str = "ea",
    ) -> None:
        self.plant = plant
        self.name = name
        self.clock = plant.clock
        self.identity = Identity(
            "EA Elektro-Automatik GmbH & Co. KG", model, SIM_SERIAL, SIM_FIRMWARE
        )
        # The rating is what the unit reports (``SYST:NOM:…?``, two decimals) and what it
        # checks set values against: a driver that sets a value at the reported nominal
        # must not be refused because the rating it was built with had more digits (a
        # computed 1565.9999999999998 W reported as 1566.00 W refused ``POW 1566``: issue 32).
        self.nominal_v = reported_rating(nominal_v)
        self.nominal_a = reported_rating(nominal_a)
        self.nominal_w = reported_rating(nominal_w)
        self.commands: list[str] = []
        self.lines: list[str] = []
        self.mute = False
        self.watchdog_trips = 0
        self.protection_trips = 0
        self._corrupt: dict[str, str] = {}
        self._parsed: dict[str, Command | None] = {}
        self._errors: deque[tuple[int, str]] = deque(maxlen=ERROR_QUEUE_LENGTH)
        self._local_lock = False
        self._ques = 0
        self._plugged = True
        self._sessions: set[_Session] = set()
        self._mon_active = False
        self._mon_timeout_s = 5.0
        self._last_line_t = self.clock.now()
        self._protections: dict[str, float] = {}
        self._reset_settings()
        self._handlers = self._build_handlers()

    # --- lifecycle (DeviceSimulator) -----------------------------------------------------
    @property
    def reachable(self) -> bool:
        """A client can connect (the network link is plugged in)."""
        return self._plugged

    def addresses(self) -> list[str]:
        return []  # served nowhere: only this process talks to it

    async def start(self) -> None:
        """Plug the link in again after :meth:`stop` (serves nothing)."""
        self._plugged = True

    async def stop(self) -> None:
        """Unplug the link: clients dropped, new connections refused; the state stays."""
        self._plugged = False
        await self.drop_clients()

    async def drop_clients(self) -> None:
        """Close every client connection (the next exchange on it fails; reconnecting works
        while the link is plugged in)."""
        for session in list(self._sessions):
            session.close()

    def open_session(self) -> _Session:
        """A new in-process client connection (see
        :class:`~supervisor.fieldbus.scpi_transport.InProcessScpiTransport`)."""
        if not self.reachable:
            raise ConnectionRefusedError(f"{self.name}: link unplugged (simulator stopped)")
        session = _Session(self)
        self._sessions.add(session)
        return session

    def check(self) -> None:
        """Enforce the interface watchdog and the protections at ``clock.now()`` (what the
        unit did on its own since the last line)."""
        self._check_watchdog()
        self._check_protections()

    # --- test hooks --------------------------------------------------------------------
    def set_local(self, local: bool) -> None:
        """Front-panel local lock: leaves remote (output off, as after remote) and refuses
        ``SYST:LOCK ON`` while set."""
        self._local_lock = local
        if local:
            self._leave_remote()

    def corrupt_next_reply(self, query: str, garbage: str = "#!garbage") -> None:
        """Answer ``garbage`` the next time ``query`` (e.g. ``MEAS:ARR?``) is asked."""
        self._corrupt[_key(query)] = garbage

    def queue_error(self, code: int, message: str | None = None) -> None:
        self._push_error(code, message)

    @property
    def remote(self) -> bool:
        return self.plant.supply.remote

    @property
    def watchdog_active(self) -> bool:
        return self._mon_active

    @property
    def ques(self) -> int:
        return self._ques

    @property
    def error_queue(self) -> list[tuple[int, str]]:
        return list(self._errors)

    # --- command lines ----------------------------------------------------------------
    def handle_line(self, raw: bytes) -> str | None:
        """Execute one command line; the reply line (without ``\\n``) or None.

        What the unit did on its own since the last line happens first (:meth:`check`).
        """
        self.check()
        self._last_line_t = self.clock.now()
        try:
            text = decode_line(raw, "ea-sim")
        except ProtocolError:
            self._push_error(ERR_COMMAND)
            return None
        _remember(self.lines, text)
        replies: list[str] = []
        queries_only = True
        for cmd_text in split_commands(text):
            _remember(self.commands, cmd_text)
            cmd = self._parse(cmd_text)
            queries_only = queries_only and cmd is not None and cmd.query
            reply = self._execute(cmd)
            if reply is not None:
                replies.append(reply)
        if not queries_only:
            # A setting may trip a protection at once. After queries alone nothing changed
            # since check() above, at this same instant: checking again cannot trip.
            self._check_protections()
        return REPLY_SEPARATOR.join(replies) if replies else None

    # --- command execution ---------------------------------------------------------------
    def _execute(self, cmd: Command | None) -> str | None:
        if cmd is None:
            self._push_error(ERR_COMMAND)
            return None
        handler = self._handlers.get((cmd.header, cmd.query))
        if handler is None or (cmd.query and cmd.argument is not None):
            self._push_error(ERR_COMMAND)
            return None
        try:
            reply = handler(cmd)
        except _Refused as exc:
            self._push_error(exc.code)
            return None
        if reply is not None and self._corrupt:
            garbage = self._corrupt.pop(cmd.header + ("?" if cmd.query else ""), None)
            if garbage is not None:
                return garbage
        return reply

    def _parse(self, text: str) -> Command | None:
        """``parse_command`` (None: not a command), remembered: a driver repeats the same
        few command texts every poll, and a dry run sends millions of them."""
        try:
            return self._parsed[text]
        except KeyError:
            pass
        try:
            cmd: Command | None = parse_command(text, "ea-sim")
        except ProtocolError:
            cmd = None
        if len(self._parsed) >= PARSE_CACHE_SIZE:
            self._parsed.clear()  # bounded: arbitrary set values make new texts
        self._parsed[text] = cmd
        return cmd

    def _build_handlers(self) -> dict[tuple[str, bool], _Handler]:
        h: dict[tuple[str, bool], _Handler] = {
            ("*IDN", True): lambda c: format_idn(self.identity),
            ("*RST", False): self._rst,
            ("*CLS", False): self._cls,
            ("*STB", True): lambda c: str(self._stb()),
            ("SYST:LOCK", False): self._lock,
            ("SYST:LOCK:OWN", True): lambda c: self._owner().value,
            ("OUTP", False): self._outp,
            ("OUTP", True): lambda c: "ON" if self.plant.supply.output_on else "OFF",
            ("SYST:NOM:VOLT", True): lambda c: f"{self.nominal_v:.{RATING_DECIMALS}f} V",
            ("SYST:NOM:CURR", True): lambda c: f"{self.nominal_a:.{RATING_DECIMALS}f} A",
            ("SYST:NOM:POW", True): lambda c: f"{self.nominal_w:.{RATING_DECIMALS}f} W",
            ("MEAS:VOLT", True): lambda c: f"{self._measure().voltage_v:.2f} V",
            ("MEAS:CURR", True): lambda c: f"{self._measure().current_a:.2f} A",
            ("MEAS:POW", True): lambda c: f"{self._measure().power_w:.2f} W",
            ("MEAS:ARR", True): lambda c: format_meas_array(self._measure()),
            ("SYST:ERR", True): self._err,
            ("STAT:QUES:COND", True): lambda c: str(self._ques),
            ("STAT:OPER:COND", True): lambda c: str(self._oper()),
            (WATCHDOG_TIME_HEADER, False): self._mon_tim,
            (WATCHDOG_TIME_HEADER, True): lambda c: f"{self._mon_timeout_s:g}",
            (WATCHDOG_ENABLE_HEADER, False): self._mon_act,
            (WATCHDOG_ENABLE_HEADER, True): lambda c: "ON" if self._mon_active else "OFF",
        }
        # Set values: header → (unit, nominal, getter, setter).
        settings: dict[str, tuple[str, float, str]] = {
            "VOLT": ("V", self.nominal_v, "volt_set_v"),
            "CURR": ("A", self.nominal_a, "curr_set_a"),
            "POW": ("W", self.nominal_w, "pow_set_w"),
            "SINK:CURR": ("A", self.nominal_a, "sink_curr_set_a"),
            "SINK:POW": ("W", self.nominal_w, "sink_pow_set_w"),
        }
        for header, (unit, nominal, attr) in settings.items():
            h[(header, False)] = self._supply_setter(unit, nominal, attr)
            h[(header, True)] = self._supply_getter(unit, attr)
        protections: dict[str, tuple[str, float]] = {
            "VOLT:PROT": ("V", self.nominal_v),
            "CURR:PROT": ("A", self.nominal_a),
            "POW:PROT": ("W", self.nominal_w),
            "SINK:CURR:PROT": ("A", self.nominal_a),
        }
        for header, (unit, nominal) in protections.items():
            h[(header, False)] = self._prot_setter(header, unit, nominal)
            h[(header, True)] = self._prot_getter(header, unit)
        return h

    def _supply_setter(self, unit: str, nominal: float, attr: str) -> _Handler:
        def handler(cmd: Command) -> None:
            value = self._setting_value(cmd, unit, nominal)
            self.plant.set_supply(**{attr: value})

        return handler

    def _supply_getter(self, unit: str, attr: str) -> _Handler:
        def handler(cmd: Command) -> str:
            value = float(getattr(self.plant.supply, attr))
            return f"{min(value, 1e9):.2f} {unit}"

        return handler

    def _prot_setter(self, header: str, unit: str, nominal: float) -> _Handler:
        def handler(cmd: Command) -> None:
            self._protections[header] = self._setting_value(cmd, unit, nominal)

        return handler

    def _prot_getter(self, header: str, unit: str) -> _Handler:
        def handler(cmd: Command) -> str:
            return f"{self._protections[header]:.2f} {unit}"

        return handler

    def _setting_value(self, cmd: Command, unit: str, nominal: float) -> float:
        self._require_remote()
        if cmd.argument is None:
            raise _Refused(ERR_PARAMETER)
        try:
            value = parse_number(cmd.argument, "ea-sim", unit)
        except ProtocolError:
            raise _Refused(ERR_PARAMETER) from None
        if value < 0 or value > nominal:
            raise _Refused(ERR_DATA_OUT_OF_RANGE)
        return value

    def _on_off(self, cmd: Command) -> bool:
        if cmd.argument is None:
            raise _Refused(ERR_PARAMETER)
        try:
            return parse_on_off(cmd.argument, "ea-sim")
        except ProtocolError:
            raise _Refused(ERR_PARAMETER) from None

    def _require_remote(self) -> None:
        if not self.plant.supply.remote:
            raise _Refused(ERR_INVALID_IN_LOCAL)

    # --- individual commands --------------------------------------------------------------
    def _rst(self, cmd: Command) -> None:
        self._reset_settings()
        self.plant.set_supply(output_on=False, volt_set_v=0.0, curr_set_a=0.0, sink_curr_set_a=0.0)

    def _cls(self, cmd: Command) -> None:
        self._errors.clear()
        self._ques = 0

    def _lock(self, cmd: Command) -> None:
        on = self._on_off(cmd)
        if on:
            if self._local_lock:
                raise _Refused(ERR_INVALID_IN_LOCAL)
            self.plant.set_supply(remote=True)
        else:
            self._leave_remote()

    def _outp(self, cmd: Command) -> None:
        on = self._on_off(cmd)
        if on:
            self._require_remote()
        self.plant.set_supply(output_on=on)

    def _err(self, cmd: Command) -> str:
        if not self._errors:
            # Reading the queue acknowledges alarms whose cause is gone (devices.md).
            self._ques = 0
            return format_error(ERR_NONE)
        code, message = self._errors.popleft()
        return format_error(code, message)

    def _mon_tim(self, cmd: Command) -> None:
        self._require_remote()
        if cmd.argument is None:
            raise _Refused(ERR_PARAMETER)
        try:
            value = parse_number(cmd.argument, "ea-sim", "s")
        except ProtocolError:
            raise _Refused(ERR_PARAMETER) from None
        if not 0 < value <= 65535:
            raise _Refused(ERR_DATA_OUT_OF_RANGE)
        self._mon_timeout_s = value

    def _mon_act(self, cmd: Command) -> None:
        self._require_remote()
        self._mon_active = self._on_off(cmd)
        self._last_line_t = self.clock.now()

    # --- state ------------------------------------------------------------------------------
    def _reset_settings(self) -> None:
        f = DEFAULT_PROTECTION_FRACTION
        self._protections = {
            "VOLT:PROT": self.nominal_v * f,
            "CURR:PROT": self.nominal_a * f,
            "POW:PROT": self.nominal_w * f,
            "SINK:CURR:PROT": self.nominal_a * f,
        }
        self._mon_active = False

    def _owner(self) -> LockOwner:
        if self.plant.supply.remote:
            return LockOwner.REMOTE
        return LockOwner.LOCAL if self._local_lock else LockOwner.NONE

    def _leave_remote(self) -> None:
        # "State after remote": OFF (POW:STAG:AFT:REM OFF).
        self.plant.set_supply(remote=False, output_on=False)

    def _push_error(self, code: int, message: str | None = None) -> None:
        self._errors.append((code, message or ERROR_MESSAGES.get(code, "Error")))

    def _stb(self) -> int:
        stb = 0
        if self._errors:
            stb |= 1 << STB_ERROR_QUEUE_BIT
        if self._ques:
            stb |= 1 << STB_QUES_BIT
        return stb

    def _measure(self) -> Measurement:
        v = self.plant.supply_voltage_v
        i = self.plant.pack_current_a
        return Measurement(v, i, v * i)

    def _oper(self) -> int:
        s = self.plant.supply
        if not self.plant.supply_energised:
            return 0
        i = self.plant.pack_current_a
        oper = 0
        if i < 0:
            oper |= 1 << OPER_SINK_BIT
        limit = s.curr_set_a if i > 0 else s.sink_curr_set_a
        if i != 0 and abs(abs(i) - limit) < _CC_TOLERANCE_A:
            oper |= 1 << OPER_CC_BIT
        else:
            oper |= 1 << OPER_CV_BIT
        return oper

    def _check_protections(self) -> None:
        if not self.plant.supply.output_on:
            return
        m = self._measure()
        tripped = 0
        if m.voltage_v > self._protections["VOLT:PROT"]:
            tripped |= 1 << QUES_OVP_BIT
        if m.current_a > self._protections["CURR:PROT"]:
            tripped |= 1 << QUES_OCP_BIT
        if -m.current_a > self._protections["SINK:CURR:PROT"]:
            tripped |= 1 << QUES_OCP_BIT
        if abs(m.power_w) > self._protections["POW:PROT"]:
            tripped |= 1 << QUES_OPP_BIT
        if tripped:
            self._ques |= tripped
            self.protection_trips += 1
            log.info("ea-sim: protection tripped (QUES 0x%04x), output off", tripped)
            self.plant.set_supply(output_on=False)

    def _check_watchdog(self) -> None:
        if not (self._mon_active and self.plant.supply.remote):
            return
        if self.clock.now() - self._last_line_t > self._mon_timeout_s:
            self.watchdog_trips += 1
            log.info("ea-sim: interface monitoring timeout, leaving remote, output off")
            self._leave_remote()


def _key(query: str) -> str:
    """Canonical form of a command for :meth:`EaSimulator.corrupt_next_reply` (header, ``?``
    for a query)."""
    try:
        cmd = parse_command(query, "ea-sim")
    except ProtocolError:
        return query.strip().upper()
    return cmd.header + ("?" if cmd.query else "")


class EaTcpSimulator(EaSimulator):
    """The same unit served on ``host:port`` (``port=0`` picks a free port, see ``.port``).

    Listens from :meth:`start` to :meth:`stop` (again on the same port after a stop); a
    checker task enforces the watchdog and the protections between commands (real clock).
    While stopped, in-process sessions are refused too.
    """

    def __init__(
        self,
        plant: BenchPlant,
        model: str = "PSB 10060-60",
        nominal_v: float = 60.0,
        nominal_a: float = 60.0,
        nominal_w: float = 1500.0,
        host: str = "127.0.0.1",
        port: int = 0,
        name: str = "ea",
    ) -> None:
        super().__init__(plant, model, nominal_v, nominal_a, nominal_w, name=name)
        self.host = host
        self._port = port
        self._plugged = False  # until it listens
        self._server: asyncio.Server | None = None
        self._checker: asyncio.Task[None] | None = None
        self._clients: dict[asyncio.Task[None], asyncio.StreamWriter] = {}

    @property
    def port(self) -> int:
        """The TCP port (the real one once started with ``port=0``)."""
        return self._port

    @property
    def running(self) -> bool:
        return self._server is not None

    def addresses(self) -> list[str]:
        return [f"EA supply {self.name}: scpi tcp {self.host}:{self._port}"]

    async def start(self) -> None:
        """Listen (again, on the same port after a ``stop()``) and start the checker."""
        if self._server is not None:
            return
        self._server = await asyncio.start_server(
            self._serve, self.host, self._port, limit=MAX_LINE_BYTES
        )
        self._port = self._server.sockets[0].getsockname()[1]
        self._plugged = True
        self._last_line_t = self.clock.now()
        self._checker = asyncio.create_task(self._check_loop(), name=f"ea-sim-{self._port}-check")

    async def stop(self) -> None:
        """Close the listener and every client; the unit keeps its state (as if unplugged
        from the network, not from mains)."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        await super().stop()  # unplugged: drops every client, sockets included
        if self._checker is not None:
            self._checker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._checker
            self._checker = None
        if server is not None:
            await server.wait_closed()

    async def drop_clients(self) -> None:
        """Close every client connection (the server keeps listening)."""
        await super().drop_clients()
        clients = list(self._clients.items())
        for _, writer in clients:
            writer.close()
        for task, _ in clients:
            task.cancel()
        for task, _ in clients:
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._clients[task] = writer
        try:
            while True:
                try:
                    raw = await reader.readuntil(b"\n")
                except (asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                    break
                reply = self.handle_line(raw)
                if reply is not None and not self.mute:
                    writer.write(reply.encode("ascii") + b"\n")
                    await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            # stop()/drop_clients() cancel this handler on purpose; end quietly (a
            # cancelled start_server callback would otherwise be logged as an error).
            pass
        finally:
            self._clients.pop(task, None)
            writer.close()
            with contextlib.suppress(OSError, asyncio.CancelledError):
                await writer.wait_closed()

    async def _check_loop(self) -> None:
        while True:
            self.check()
            await self.clock.sleep_until(self.clock.now() + CHECK_PERIOD_S)


def _remember(log: list[str], text: str) -> None:
    log.append(text)
    if len(log) > LINE_LOG_LENGTH:
        del log[: len(log) - LINE_LOG_LENGTH // 2]
