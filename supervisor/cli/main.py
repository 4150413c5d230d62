"""``supervisor`` command line.

Exit codes: 0 success, 1 runtime failure, 2 usage or configuration error. A user
mistake gets one clear message naming file:line:col, never a traceback.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import faulthandler
import io
import logging
import math
import os
import re
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, NoReturn

from supervisor.bench import args as bench_args
from supervisor.cli import audit, ctl, fleet, modbus, notify
from supervisor.config.limits import MAX_SCAN_PERIOD_S, MIN_SCAN_PERIOD_S
from supervisor.core.encoding import StorableFormatter
from supervisor.core.errors import ConfigError, ConfigErrors, SupervisorError
from supervisor.core.logrepeat import RepeatFilter

if TYPE_CHECKING:
    from collections.abc import Mapping

    from supervisor.app.service import Supervisor
    from supervisor.config.models import BenchConfig
    from supervisor.core.units import Dim

log = logging.getLogger("supervisor")

DEFAULT_IO_MAP = Path("io_maps/sim.yaml")
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def _err(msg: str) -> None:
    sys.stderr.write(msg.rstrip("\n") + "\n")


def _out(msg: str) -> None:
    sys.stdout.write(msg.rstrip("\n") + "\n")
    sys.stdout.flush()


LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


def _setup_logging(level: str, *, off_thread: bool = False) -> None:
    """Log lines to stderr, as ``logging.basicConfig`` does (nothing when the root logger
    has a handler already: a test's). ``off_thread``: formatted and written by a thread of
    their own (``QueueHandler`` → ``QueueListener``), for ``supervisor run``: the scan's
    thread only hands each record over. A write to stderr is a system call that lets the
    interpreter lock go, and a step change of 16 channels in one scan logged 16 lines on
    the scan's thread, each a chance for a publisher's thread to keep the lock up to the
    switch interval (issue 13, ADR 0021). The listener writes what is queued before the
    process exits (``atexit``).

    Repeated lines are collapsed (``RepeatFilter``: one line of a kind per 10 s, with the
    count of those suppressed; issue 27: a connection flood wrote 71,567 "Too many open
    files" lines). The filter sits before the queue: a suppressed line (a traceback) is
    not even formatted."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(StorableFormatter(LOG_FORMAT))  # core/encoding.py
    repeats = RepeatFilter(time.monotonic)
    if off_thread:
        # Imported here (with socket and pickle): only ``run`` logs off its thread.
        import queue
        from logging.handlers import QueueHandler, QueueListener

        records: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
        listener = QueueListener(records, handler)
        listener.start()
        atexit.register(listener.stop)
        queued = QueueHandler(records)
        queued.addFilter(repeats)
        root.addHandler(queued)
    else:
        handler.addFilter(repeats)
        root.addHandler(handler)
    root.setLevel(getattr(logging, level.upper(), logging.INFO))


# --- run -----------------------------------------------------------------------------
async def _run(args: argparse.Namespace) -> int:
    """``supervisor run``: the supervisor the composition root builds
    (``supervisor.app.service``), told about on stdout, run until SIGINT/SIGTERM."""
    from supervisor.app.lock import BenchBusy, BenchLockFailed
    from supervisor.app.service import build_supervisor
    from supervisor.devices.registry import load_bench

    cfg = load_bench(args.io_map)
    descriptors = _descriptors_fit(cfg)
    if descriptors is None:
        return EXIT_USAGE
    try:
        # One bench, one supervisor (docs/design.md "Safety"): its lock is taken first, before
        # anything touches a device, a simulator or a port; the kernel drops it when this
        # process dies. Before anything runs, a test that was under way comes back Held.
        sup = build_supervisor(
            cfg,
            simulate=not args.no_sim,
            http_port=args.http_port,
            display_period_s=10.0 if args.verbose else 60.0,
        )
    except (BenchBusy, BenchLockFailed) as exc:
        _err(f"supervisor: {exc}")
        return EXIT_USAGE
    try:
        # Said once the bench is this process's: a second supervisor refused by the lock
        # prints nothing on stdout.
        _out(descriptors)
        return await _serve(args, cfg, sup)
    finally:
        sup.release()


def _descriptors_fit(cfg: BenchConfig) -> str | None:
    """Raise the soft ``RLIMIT_NOFILE`` (towards 8192, within the hard limit) and check that
    the listeners' caps leave the devices their descriptors (issue 27, finding 3): the line
    that says so, or None (said on stderr) when they do not fit."""
    from supervisor.app.descriptors import descriptor_budget
    from supervisor.core.descriptors import raise_soft_limit

    limit = raise_soft_limit()
    budget = descriptor_budget(cfg)
    problem = budget.problem(limit)
    if problem is not None:
        _err(f"supervisor: {problem}")
        return None
    raised = f", raised from {limit.before}" if limit.before != limit.soft else ""
    return (
        f"file descriptors: soft limit {limit.soft}{raised}; the caps take at most"
        f" {budget.describe()}"
    )


async def _serve(args: argparse.Namespace, cfg: BenchConfig, sup: Supervisor) -> int:
    import asyncio

    from supervisor.commands import Verb

    starts: list[str] = []
    for spec in args.recipe:
        channel, _, file = spec.partition("=")
        if not file:
            raise ConfigError(f"--recipe {spec!r}: expected CHANNEL=FILE, e.g. ch0=recipes/x.yaml")
        # Loaded before anything is served; ``--start`` starts it once the channel's
        # inputs read GOOD (``supervisor.app.service.start_when_ready``).
        verb = Verb.START if args.start else Verb.LOAD
        result = await sup.load(channel, file, _params(args.param))
        if args.start:
            starts.append(channel)
        if not result.accepted:
            _err(f"supervisor: --recipe {spec}: {verb.value} refused: {result.reason}")
            for line in result.details[1:]:
                _err(f"  {line}")
            return EXIT_USAGE
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    # `kill -USR2 <pid>`: every asyncio task's stack into the log (what it waits for).
    loop.add_signal_handler(signal.SIGUSR2, _dump_tasks)
    try:
        await sup.start()
    except OSError as exc:
        _err(f"supervisor: cannot listen: {exc.strerror or exc} ({exc})")
        return EXIT_USAGE
    _banner(args, cfg, sup)
    _out("Ctrl-C or SIGTERM stops the bench; every output goes to its safe state.")
    unconfirmed = await sup.run(stop, starts)
    if unconfirmed:
        # Said only when every device confirmed it: an unreachable supply is not "safe".
        for device, why in unconfirmed.items():
            _out(f"stopped: safe state NOT confirmed for {device}: {why}")
        return EXIT_FAIL
    _out("stopped: all outputs safe")
    return EXIT_OK


def _banner(args: argparse.Namespace, cfg: BenchConfig, sup: Supervisor) -> None:
    """What listens where, what was restored, where the history goes (stdout)."""
    bench, api, opcua = sup.bench, sup.api, sup.opcua
    _out(
        f"bench {cfg.bench!r}: {len(bench.db)} tags, {len(bench.channels)} channels,"
        f" scan period {cfg.scan.period_s * 1000:g} ms"
    )
    _out(f"HTTP API listening on {api.url}/tags")
    login = sup.screens.access.users
    _out(
        f"operator screens: http://{api.host}:{api.port}/ ("
        + (f"login: the users of {login.path}" if login is not None else "no login")
        + ")"
    )
    if login is not None and not len(login):
        _out(f"no users yet: supervisor opcua add-user NAME --role operator --io-map {args.io_map}")
    if opcua is not None:
        _out(f"OPC UA server listening on {opcua.endpoint} (namespace {opcua.namespace})")
    if sup.modbus is not None and cfg.modbus_server is not None:
        ms = cfg.modbus_server
        writers = ", ".join(ms.writers) or "no address"
        writes = f"writes from {writers}" if ms.writes else "read only"
        _out(f"Modbus TCP server listening on {sup.modbus.endpoint} (unit {ms.unit_id}, {writes})")
    if bench.sim is not None and bench.sim.served:
        for line in bench.sim.addresses():
            _out(f"simulated {line}")
        _out(f'simulated e-stop button: PUT {api.url}/sim/estop {{"pressed": true}}')
    for line in sup.restored:
        _out(f"retained state: {line}")
    if bench.historian is not None:
        _out(f"history: {bench.historian.path} ({api.url}/history, {api.url}/events)")
    if bench.influx is not None:
        influx = bench.influx.settings
        waiting = bench.influx.spool.counts().waiting
        _out(
            f"InfluxDB: {influx.url} bucket {influx.bucket!r}, spool {influx.spool_path}"
            f" ({waiting} points waiting)"
        )


def _dump_tasks() -> None:
    import asyncio

    for task in asyncio.all_tasks():
        log.warning("task %s:", task.get_name())
        task.print_stack(file=sys.stderr)


def cmd_run(args: argparse.Namespace) -> int:
    # Imported by the command that runs a bench, not by the parser (issue 30: each command
    # imports what it needs; ``check`` none of the scan's or the lab's modules, nor asyncio).
    import asyncio

    from supervisor.bench import memtrace
    from supervisor.scan.engine import ScanFirstLoop

    _setup_logging(args.log_level, off_thread=True)
    # A debugging switch, off unless $SUPERVISOR_TRACEMALLOC names a folder (bench/memtrace.py).
    trace = memtrace.start_from_env()
    # A bench runs for days: `kill -USR1 <pid>` prints every thread's stack to the log
    # (what a stuck supervisor is doing), without stopping it.
    with contextlib.suppress(io.UnsupportedOperation, AttributeError, ValueError):
        # (a captured stderr has no file descriptor: then no stack dumps, nothing else lost)
        faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map (give a path, e.g. io_maps/sim.yaml)")
        return EXIT_USAGE
    try:
        # The scan's loop runs a scan that falls due before its next callback (ADR 0023).
        with asyncio.Runner(loop_factory=ScanFirstLoop) as runner:
            return runner.run(_run(args))
    finally:
        if trace is not None:
            trace.stop()


# --- sim -----------------------------------------------------------------------------
async def _sim(args: argparse.Namespace) -> int:
    import asyncio

    from supervisor.app.simulation import build_simulation
    from supervisor.core.clock import RealClock
    from supervisor.devices.registry import load_bench
    from supervisor.hmi import HttpApi
    from supervisor.tags import TagDB

    cfg = load_bench(args.io_map)
    clock = RealClock()
    sim = build_simulation(cfg, clock)
    if sim is None or not sim.served:
        _err(f"{args.io_map}: no device has sim: true; nothing to serve")
        return EXIT_USAGE
    # The map's port (default 0: a free one, printed below), unless --control-port says.
    port = args.control_port
    if port is None:
        port = cfg.simulation.control_port if cfg.simulation is not None else 0
    control = HttpApi(TagDB(), clock, "127.0.0.1", port, estop=sim.press_estop, sim_state=sim.state)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await sim.start()
        await control.start()
    except OSError as exc:
        _err(f"supervisor sim: cannot listen: {exc.strerror or exc} ({exc})")
        await sim.stop()
        await control.stop()
        return EXIT_USAGE
    for line in sim.addresses():
        _out(line)
    _out(f'e-stop button: PUT {control.url}/sim/estop {{"pressed": true}}')
    _out(f"plant state: GET {control.url}/sim/state")
    try:
        await stop.wait()
    finally:
        await control.stop()
        await sim.stop()
        sim.release()
    _out("simulators stopped")
    return EXIT_OK


def cmd_sim(args: argparse.Namespace) -> int:
    import asyncio

    _setup_logging(args.log_level)
    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map")
        return EXIT_USAGE
    return asyncio.run(_sim(args))


# --- check ---------------------------------------------------------------------------
Checked = tuple[list[ConfigError], tuple[ConfigError, ...], list[str]]
"""A file's errors, a recipe's warnings (a parameter nothing reads), an I/O map's network
exposure (warnings too)."""


def _check_map(path: Path, tags: dict[str, Dim]) -> Checked:
    """An I/O map's errors and exposure; its tags' dimensions added to ``tags``."""
    from supervisor.config.exposure import exposure_warnings
    from supervisor.devices.registry import load_bench

    try:
        cfg = load_bench(path)
    except ConfigErrors as exc:
        return exc.errors, (), []
    tags.update(_tag_dims(cfg))
    return [], (), exposure_warnings(cfg)


def _tag_dims(cfg: BenchConfig) -> dict[str, Dim]:
    """The dimension of each tag an I/O map maps (what a recipe's condition may compare it
    with), as the bench it builds gives them (``Bench.tag_dims``)."""
    from supervisor.core.units import UNITS, Dim

    out: dict[str, Dim] = {}
    for m in cfg.tags:
        info = cfg.devices[m.device].points().get(m.point)
        if m.threshold is not None or (info is not None and info.dtype == "bool"):
            out[m.name] = Dim.BOOL
        elif info is not None and info.dtype in ("float", "int"):
            dim, factor = UNITS.get(m.unit, (Dim.NONE, 1.0))
            out[m.name] = dim if factor == 1.0 else Dim.NONE
    return out


def _check_recipe(path: Path, data: Any, pos: Any, tags: Mapping[str, Dim]) -> Checked:
    """A recipe's errors and warnings; the bench tags it may name: ``tags``."""
    from supervisor.chains.compiler import Target, compile_recipe
    from supervisor.config.recipe import recipe_of

    try:
        # The document parsed once (load_recipe's checks), not the file read again.
        recipe = recipe_of(data, pos, str(path))
        target = Target(tags=tags) if tags else None
        return [], compile_recipe(recipe, pos, str(path), target).warnings, []
    except ConfigErrors as exc:
        return exc.errors, (), []
    except ConfigError as exc:
        return [exc], (), []


def check_files(paths: Sequence[Path]) -> list[Checked]:
    """Each file's :data:`Checked`, in order. The I/O maps first: a recipe may name the tags
    of the maps checked with it (``supervisor check io_maps/sim.yaml recipes/x.yaml``: a
    condition on ``bms.cell_max``). Each kind of file imports only what checks it: a recipe
    neither the device kinds nor the I/O map's models (issue 30)."""
    from supervisor.config.yamlpos import load_yaml

    out: dict[int, Checked] = {}
    recipes: list[tuple[int, Any, Any]] = []
    tags: dict[str, Dim] = {}
    for k, path in enumerate(paths):
        try:
            data, pos = load_yaml(path)
        except ConfigError as exc:
            out[k] = ([exc], (), [])
            continue
        if isinstance(data, dict) and "recipe" in data:
            recipes.append((k, data, pos))
        else:
            out[k] = _check_map(path, tags)
    for k, data, pos in recipes:
        out[k] = _check_recipe(paths[k], data, pos, tags)
    return [out[k] for k in range(len(paths))]


def cmd_check(args: argparse.Namespace) -> int:
    bad = 0
    for f, (errors, warnings, exposure) in zip(
        args.files, check_files([Path(f) for f in args.files]), strict=True
    ):
        for w in warnings:
            _err(f"warning: {w.location_message()}")
        for e in errors:
            _err(e.location_message())
        for x in exposure:  # a warning, not an error: the exit code stays 0
            _err(f"{f}: warning: {x}")
        if errors:
            bad += 1
        else:
            _out(f"{f}: OK")
    return EXIT_USAGE if bad else EXIT_OK


# --- schema --------------------------------------------------------------------------
def cmd_schema(args: argparse.Namespace) -> int:
    from supervisor.config.schema import write_schemas
    from supervisor.devices.registry import BENCH_MODEL

    for path in write_schemas(Path(args.out), BENCH_MODEL):
        _out(f"wrote {path}")
    return EXIT_OK


# --- dry-run -------------------------------------------------------------------------
# Argument types: a bad value is one line naming the option and what was received, exit 2
# (argparse prints "supervisor dry-run: error: argument --soc: ..."), never a traceback.
DRY_RUN_MAX_HOURS: Final = 100_000.0
"""The longest dry run asked for (about 11 years of virtual time)."""
DRY_RUN_MAX_CELLS: Final = 1000
"""Li-ion cells in series a dry run models at most (a 4.35 kV pack)."""
DRY_RUN_MAX_CAPACITY_AH: Final = 100_000.0
"""The largest rated capacity a dry run models (a 100 kAh bank)."""
DRY_RUN_MIN_CAPACITY_AH: Final = 0.001
"""The smallest (1 mAh, below any coin cell): ``1e-300`` made the model's voltage NaN."""
_TIME_OF_DAY = re.compile(r"([01]?[0-9]|2[0-3]):([0-5][0-9])", re.ASCII)
_CONTROL_CHAR = re.compile(r"[\x00-\x1f\x7f-\x9f]")


_NUMBER = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?", re.ASCII)


def _finite(text: str) -> float:
    """A finite number in ASCII digits (``float()`` would also take ``nan``, ``1_000``, ``٣``)."""
    t = text.strip()
    if _NUMBER.fullmatch(t) is None:
        what = (
            "a finite number"
            if t.lower().lstrip("+-") in ("nan", "inf", "infinity")
            else "a number"
        )
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    value = float(t)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _bounded(
    low: float, high: float, unit: str = "", *, low_included: bool = True
) -> Callable[[str], float]:
    """An argparse type: a finite number in [low, high] (or (low, high])."""
    u = f" {unit}" if unit else ""

    def parse(text: str) -> float:
        value = _finite(text)
        if (value < low if low_included else value <= low) or value > high:
            span = (
                f"from {low:g} to {high:g}{u}"
                if low_included
                else f"more than {low:g} and at most {high:g}{u}"
            )
            raise argparse.ArgumentTypeError(f"expected a number {span}, got {text!r}")
        return value

    return parse


def _cells(text: str) -> int:
    if not re.fullmatch(r"[0-9]{1,6}", text.strip(), re.ASCII):
        raise argparse.ArgumentTypeError(f"expected a whole number of cells, got {text!r}")
    cells = int(text)
    if not 1 <= cells <= DRY_RUN_MAX_CELLS:
        raise argparse.ArgumentTypeError(
            f"expected from 1 to {DRY_RUN_MAX_CELLS} cells in series, got {text!r}"
        )
    return cells


def _time_of_day(text: str) -> str:
    # Spaces around are forgiven; a newline or another control character is not (stripped,
    # "08:00\n" was accepted).
    m = None if _CONTROL_CHAR.search(text) else _TIME_OF_DAY.fullmatch(text.strip())
    if m is None:
        raise argparse.ArgumentTypeError(
            f"expected a time of day HH:MM (00:00 to 23:59), got {text!r}"
        )
    return f"{int(m[1]):02d}:{m[2]}"


def _results_dir(text: str) -> str:
    """A folder the result files can go to: it exists as a writable folder, or can be made
    under the nearest existing folder (checked before the dry run, not after hours)."""
    path = Path(text)
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text!r}: cannot write in {existing}")
    try:
        # A test's folder is made in it: tried now (``/proc`` passes the checks above and
        # takes no folder; the recorder failed at the first record, issue 28).
        path.mkdir(parents=True, exist_ok=True)
        Path(tempfile.mkdtemp(prefix=".supervisor-probe-", dir=path)).rmdir()
    except OSError as exc:
        raise argparse.ArgumentTypeError(
            f"{text!r}: cannot make a folder in it: {exc.strerror or exc}"
        ) from None
    return text


def _params(items: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--param {item!r}: expected NAME=VALUE, e.g. v_max=1.8V")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def cmd_dry_run(args: argparse.Namespace) -> int:
    import asyncio

    from supervisor.app.dryrun import dry_run, format_report

    _setup_logging("warning")
    if not Path(args.recipe).exists():
        _err(f"{args.recipe}: no such recipe")
        return EXIT_USAGE
    io_map = None
    if args.io_map is not None:
        from supervisor.devices.registry import load_bench

        if args.model is not None or args.cells != 1:
            _err("--model and --cells are the built-in bench's; --io-map runs the map's plant")
            return EXIT_USAGE
        io_map = load_bench(args.io_map)  # ConfigErrors: said as `supervisor check` says them
    elif args.channel is not None:
        _err("--channel names a channel of the I/O map given with --io-map")
        return EXIT_USAGE
    res = asyncio.run(
        dry_run(
            args.recipe,
            model=args.model,
            params=_params(args.param),
            capacity_ah=args.capacity_ah,
            soc=args.soc,
            cells=args.cells,
            period_s=args.period_s,
            start=args.start,
            max_hours=args.max_hours,
            results_dir=Path(args.results) if args.results else None,
            io_map=io_map,
            channel=args.channel,
        )
    )
    for line in format_report(res):
        _out(line)
    # 1: the run stopped at --max-hours with the chain still going (no duration predicted).
    return EXIT_OK if res.finished else EXIT_FAIL


# --- import ----------------------------------------------------------------------------
def _write_or_print(text: str, out: str | None) -> None:
    if out is None:
        sys.stdout.write(text if text.endswith("\n") else text + "\n")
        return
    path = Path(out)
    if path.exists():
        raise ConfigError(f"{out}: already exists; choose another name or remove it first")
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:  # a missing folder, no permission (issue 28: a traceback)
        raise ConfigError(f"cannot write: {exc.strerror or exc}", out) from None
    _err(f"wrote {out}")


def cmd_import(args: argparse.Namespace) -> int:
    if not Path(args.file).exists():
        _err(f"{args.file}: no such file")
        return EXIT_USAGE
    if args.kind == "chadeche":
        from supervisor.importers import import_chadeche

        if args.prm is not None and not Path(args.prm).exists():
            _err(f"{args.prm}: no such parameter file")
            return EXIT_USAGE
        overrides = {}
        for item in args.option:
            letter, _, value = item.partition("=")
            if not value:
                raise ConfigError(f"--option {item!r}: expected LETTER=VALUE, e.g. i=1300")
            overrides[letter] = value
        res = import_chadeche(args.file, args.prm, name=args.name, overrides=overrides)
        for w in res.warnings:
            _err(f"warning: {w}")
        _write_or_print(res.yaml_text, args.output)
        if res.calibration_snippet:
            _err("calibration (-1 -2 -s -o) belongs to the I/O map, under the board:")
            _err(res.calibration_snippet)
        return EXIT_OK
    from supervisor.importers.profile import import_profile_noting

    text, notices = import_profile_noting(args.file, name=args.name, output=args.output)
    for notice in notices:  # also in the recipe, as "# note:" lines
        _err(f"note: {notice}")
    _write_or_print(text, args.output)
    return EXIT_OK


# --- calibrate -------------------------------------------------------------------------
def _staircase_ma(recipe_path: str) -> list[float]:
    from supervisor.chains.compiler import compile_recipe
    from supervisor.config.recipe import load_recipe

    recipe, pos = load_recipe(recipe_path)
    program = compile_recipe(recipe, pos, recipe_path)
    return [abs(st.current_a) * 1000 for st in program.steps if st.kind in ("charge", "rest")]


def _ask(prompt: str) -> float:
    while True:
        sys.stderr.write(prompt)
        sys.stderr.flush()
        line = sys.stdin.readline()
        if not line:
            raise ConfigError("calibration: input ended before every reading was given")
        try:
            return float(line.strip().replace(",", "."))
        except ValueError:
            _err(f"  {line.strip()!r} is not a number; type the reading again")


def cmd_calibrate(args: argparse.Namespace) -> int:
    from supervisor.app.calibrate import (
        calibrate_current,
        calibrate_voltage,
        fit_line,
        read_pairs_csv,
        write_calibration,
    )

    if args.csv:
        xs, ys = read_pairs_csv(args.csv)
    elif args.what == "current":
        recipe = args.recipe or "recipes/current-calibration.yaml"
        xs = _staircase_ma(recipe)
        _err(f"staircase of {recipe}: type the ammeter reading (mA) for each setpoint")
        ys = [_ask(f"  setpoint {x:g} mA → measured mA: ") for x in xs]
    else:
        recipe = args.recipe or "recipes/voltage-calibration.yaml"
        steps = _staircase_ma(recipe)
        _err(f"staircase of {recipe}: for each step type the supervisor's V, then the meter's V")
        xs, ys = [], []
        for x in steps:
            xs.append(_ask(f"  step {x:g} mA → voltage shown by the supervisor (V): "))
            ys.append(_ask(f"  step {x:g} mA → voltmeter reading (V): "))
    try:
        if args.what == "current":
            # seed §III.F.1: setpoint as a function of the measured current
            slope, offset = calibrate_current(xs, ys)
            values = {"current_slope": slope, "current_offset_ma": offset}
            _, _, r2 = fit_line(ys, xs)
        else:
            slope, offset = calibrate_voltage(xs, ys)
            values = {"voltage_slope": slope, "voltage_offset_v": offset}
            _, _, r2 = fit_line(xs, ys)
    except ValueError as exc:
        raise ConfigError(f"calibration: {exc}") from None
    _out(f"fit: slope {slope:.6f}, offset {offset:.6f}, r² {r2:.6f}")
    for k, v in values.items():
        _out(f"  {k}: {v:.6f}")
    if args.io_map:
        before = _text_or_none(args.io_map)
        write_calibration(args.io_map, args.device, args.board, values)
        _out(f"written to {args.io_map}: device {args.device!r}, board {args.board}")
        _audit_calibration(args, values, before)
    return EXIT_OK


def _text_or_none(path: str) -> str | None:
    try:
        return Path(path).read_text("utf-8", "surrogateescape")
    except OSError:
        return None


def _audit_calibration(
    args: argparse.Namespace, values: dict[str, float], before: str | None
) -> None:
    """The calibration written into the I/O map, into that bench's audit trail: the values,
    and the map's SHA-256 and diff against what it was."""
    from supervisor.audit import text_change
    from supervisor.devices.registry import load_bench

    after = _text_or_none(args.io_map) or ""
    try:
        state_dir = load_bench(args.io_map).state_dir
    except ConfigErrors as exc:  # written, yet refused: say it, the audit has no folder
        _err(f"warning: calibration not recorded in the audit log: {exc.errors[0]}")
        return
    change = text_change(before, after, Path(args.io_map).name)
    target = f"{args.device} board {args.board}"
    details = {"io_map": str(Path(args.io_map).resolve()), "values": values, **change}
    audit.record(state_dir, "calibration.write", target, details)


# --- bench ---------------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    from supervisor.bench.command import run_bench

    _setup_logging("warning")
    return run_bench(args, DEFAULT_IO_MAP)


# --- opcua ---------------------------------------------------------------------------------
def cmd_opcua(args: argparse.Namespace) -> int:
    """``supervisor opcua add-user|remove-user|list-users``: the OPC UA users file of a bench
    (hashes only; ``<state_dir>/opcua/users.yaml`` unless its I/O map names another)."""
    from supervisor.config.users import read_users
    from supervisor.devices.registry import load_bench
    from supervisor.publish.opcua import OpcUaSettings, add_user, remove_user

    if args.action == "selftest":
        return _opcua_selftest(args)
    if not Path(args.io_map).exists():
        _err(f"{args.io_map}: no such I/O map (give a path, e.g. io_maps/sim.yaml)")
        return EXIT_USAGE
    if args.action != "list-users" and not args.name:
        _err(f"supervisor opcua {args.action}: give the user's name")
        return EXIT_USAGE
    cfg = load_bench(args.io_map)
    path = OpcUaSettings.of(cfg).users_file
    if args.action == "list-users":
        for name, entry in sorted(read_users(path).items()):
            _out(f"{name}\t{entry.role}")
        return EXIT_OK
    if args.action == "remove-user":
        if not remove_user(path, args.name):
            _err(f"{path}: no user {args.name!r}")
            return EXIT_USAGE
        _out(f"{path}: user {args.name} removed")
        audit.record(cfg.state_dir, "user.remove", args.name, {"users_file": str(path)})
        return EXIT_OK
    if args.password_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
    else:
        import getpass

        password = getpass.getpass(f"password for {args.name}: ")
        if getpass.getpass("again: ") != password:
            _err("the two passwords differ; nothing written")
            return EXIT_USAGE
    new = add_user(path, args.name, args.role, password)
    _out(f"{path}: user {args.name} ({args.role}) {'added' if new else 'updated'}")
    what = {"role": args.role, "new": new, "users_file": str(path)}  # never the password
    audit.record(cfg.state_dir, "user.add", args.name, what)
    return EXIT_OK


def _opcua_selftest(args: argparse.Namespace) -> int:
    """``supervisor opcua selftest URL``: PASS/FAIL/SKIP per check; 1 when one failed."""
    import asyncio

    from supervisor.cli.selftest import selftest

    if not args.name.startswith("opc.tcp://"):
        _err(
            "supervisor opcua selftest: give the server's URL (opc.tcp://HOST:PORT),"
            f" not {args.name!r}"
        )
        return EXIT_USAGE
    password = None
    if args.user:
        if args.password_stdin:
            password = sys.stdin.readline().rstrip("\r\n")
        else:
            import getpass

            password = getpass.getpass(f"password for {args.user}: ")
    # asyncua logs the faults the checks provoke on purpose (Bad_TooManyOperations …): the
    # integrator reads the checks' lines, one each.
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    try:
        outcomes = asyncio.run(selftest(args.name, args.user, password))
    except (OSError, TimeoutError) as exc:
        _err(f"cannot reach {args.name}: {exc or type(exc).__name__}")
        return EXIT_USAGE
    except Exception as exc:  # asyncua's refusals (login, endpoint): one line, no traceback
        _err(f"{args.name}: {type(exc).__name__}: {exc}")
        return EXIT_USAGE
    for outcome in outcomes:
        _out(outcome.line())
    failed = sum(o.verdict == "FAIL" for o in outcomes)
    passed = sum(o.verdict == "PASS" for o in outcomes)
    _out(f"{passed} passed, {failed} failed, {len(outcomes) - passed - failed} skipped")
    return 1 if failed else EXIT_OK


class _Parser(argparse.ArgumentParser):
    """A usage error is one line (the option, what was received, where to read more), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _add_record_parsers(sub: Any) -> None:
    """Register what checks the records: ``supervisor results verify DIR…``,
    ``supervisor audit verify|export`` (cli/audit.py) and ``supervisor notify test``
    (cli/notify.py: it records its outcome in the audit trail)."""
    rs = sub.add_parser("results", help="result folders: verify DIR (complete and unmodified)")
    rs.add_argument("action", choices=["verify"])
    rs.add_argument("folders", nargs="+", metavar="DIR", help="a test's result folder")
    rs.set_defaults(func=cmd_results)
    audit.add_parser(sub, DEFAULT_IO_MAP)
    notify.add_parser(sub, DEFAULT_IO_MAP)
    fleet.add_parser(sub)


def _add_opcua_parser(sub: Any) -> None:
    """Register ``supervisor opcua`` (a bench's OPC UA users, and the selftest of a
    server) on the main parser's subcommands."""
    ou = sub.add_parser(
        "opcua",
        help="OPC UA: the users of a bench (add-user, remove-user, list-users); selftest URL"
        " (what an integrator's client expects of a server)",
    )
    ou.add_argument("action", choices=["add-user", "remove-user", "list-users", "selftest"])
    ou.add_argument(
        "name",
        nargs="?",
        default="",
        help="the user (add-user, remove-user); the server's URL (selftest)",
    )
    ou.add_argument("--user", default=None, help="selftest: log in as this user (methods)")
    ou.add_argument("--role", choices=["viewer", "operator", "engineer"], default="viewer")
    ou.add_argument("--io-map", default=str(DEFAULT_IO_MAP), help="the bench whose users")
    ou.add_argument(
        "--password-stdin", action="store_true", help="read the password from stdin (scripts)"
    )
    ou.set_defaults(func=cmd_opcua)


def _add_dry_run_parser(sub: Any) -> None:
    """``supervisor dry-run``'s arguments."""
    d = sub.add_parser(
        "dry-run",
        help="run a recipe against the battery model, virtual time",
        description="Run a recipe against the battery model on the virtual clock: step"
        " timeline, predicted duration, capacity per cycle.",
        epilog="exit codes: 0 the recipe came to an end (Complete, Stopped, Aborted, or Held"
        " by an alarm: the report says which); 1 it did not finish within --max-hours (the"
        " report says where it was: step, cycle, test time); 2 a usage or recipe error."
        " A long run's timeline and cycles are shown by their first and last halves.",
    )
    d.add_argument("recipe")
    d.add_argument("--model", choices=["nimh-aa", "liion-pack"], default=None)
    d.add_argument(
        "--io-map",
        default=None,
        metavar="MAP",
        help="run on a channel of this I/O map: its own supply, battery and sensors, simulated",
    )
    d.add_argument(
        "--channel", default=None, help="the I/O map's channel (default: its only channel)"
    )
    d.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    d.add_argument(
        "--capacity-ah",
        type=_bounded(DRY_RUN_MIN_CAPACITY_AH, DRY_RUN_MAX_CAPACITY_AH, "Ah"),
        default=None,
        help="rated capacity of the cell",
    )
    d.add_argument(
        "--soc", type=_bounded(0.0, 1.0), default=None, help="state of charge at start, 0..1"
    )
    d.add_argument("--cells", type=_cells, default=1, help="Li-ion cells in series")
    d.add_argument(
        "--period-s",
        type=_bounded(MIN_SCAN_PERIOD_S, MAX_SCAN_PERIOD_S, "s"),
        default=1.0,
        help="scan period of the dry run",
    )
    d.add_argument(
        "--start", type=_time_of_day, default="08:00", help="local time of day the test starts"
    )
    d.add_argument(
        "--max-hours",
        type=_bounded(0.0, DRY_RUN_MAX_HOURS, "h", low_included=False),
        default=1000.0,
        help="stop the dry run after this much virtual time (default 1000 h; exit 1)",
    )
    d.add_argument(
        "--results", type=_results_dir, default=None, help="write result files under this folder"
    )
    d.set_defaults(func=cmd_dry_run)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="supervisor", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="run a bench until Ctrl-C/SIGTERM")
    r.add_argument("io_map", nargs="?", default=str(DEFAULT_IO_MAP))
    r.add_argument("--http-port", type=int, default=None, help="override hmi.port (0 = any)")
    r.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    r.add_argument("--recipe", action="append", default=[], metavar="CHANNEL=FILE")
    r.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    r.add_argument(
        "--start",
        action="store_true",
        help="start the --recipe chains once their channels' inputs read GOOD",
    )
    r.add_argument("-v", "--verbose", action="store_true", help="status line every 10 s")
    r.add_argument(
        "--no-sim",
        action="store_true",
        help="do not start the simulators of sim: true devices (supervisor sim serves them)",
    )
    r.set_defaults(func=cmd_run)

    sm = sub.add_parser("sim", help="serve the simulated devices of an I/O map, alone")
    sm.add_argument("io_map", nargs="?", default=str(DEFAULT_IO_MAP))
    sm.add_argument(
        "--control-port",
        type=int,
        default=None,
        help="e-stop button API port (default: the map's simulation.control_port; 0 picks a"
        " free one, printed)",
    )
    sm.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    sm.set_defaults(func=cmd_sim)

    c = sub.add_parser("check", help="validate I/O maps and recipes; exit 2 on error")
    c.add_argument("files", nargs="+")
    c.set_defaults(func=cmd_check)

    s = sub.add_parser("schema", help="write the JSON Schemas editors use")
    s.add_argument("--out", default=".", help="project root: writes io_maps/ and recipes/ schemas")
    s.set_defaults(func=cmd_schema)

    _add_dry_run_parser(sub)

    im = sub.add_parser("import", help="turn a Chadèche sequence file or a profile into YAML")
    im.add_argument("kind", choices=["chadeche", "profile"])
    im.add_argument("file")
    im.add_argument("--prm", default=None, help="chadecheN.prm parameter file")
    im.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="LETTER=VALUE",
        help="a chadeche command-line option, overrides the .prm (e.g. i=1300, M=1.8)",
    )
    im.add_argument("--name", default=None, help="recipe name (default: from the file name)")
    im.add_argument("-o", "--output", default=None, help="write the recipe here (default: stdout)")
    im.set_defaults(func=cmd_import)

    ca = sub.add_parser("calibrate", help="fit a·x+b from a calibration staircase")
    ca.add_argument("what", choices=["current", "voltage"])
    ca.add_argument("--csv", default=None, help="pairs: setpoint,measured (or ADC V,meter V)")
    ca.add_argument("--recipe", default=None, help="staircase recipe (readings typed in)")
    ca.add_argument("--io-map", default=None, help="write the coefficients into this I/O map")
    ca.add_argument("--device", default="chadeche")
    ca.add_argument("--board", type=int, default=0)
    ca.set_defaults(func=cmd_calibrate)

    _add_opcua_parser(sub)

    _add_record_parsers(sub)
    ctl.add_parser(sub)
    modbus.add_parser(sub)

    bench_args.add_parser(sub).set_defaults(func=cmd_bench)
    return p


def cmd_results(args: argparse.Namespace) -> int:
    """``results verify DIR...``: 0 when every folder is complete and unmodified, 1 when one
    is not (each problem said), 2 when a path is not a test's result folder."""
    from supervisor.publish.provenance import NotAResultFolder, verify

    code = EXIT_OK
    for folder in args.folders:
        try:
            v = verify(Path(folder))
        except NotAResultFolder as exc:
            _err(f"supervisor results verify: {exc}")
            return EXIT_USAGE
        except OSError as exc:
            _err(f"supervisor results verify: {folder}: cannot read: {exc.strerror or exc}")
            return EXIT_USAGE
        if v.ok:
            _out(f"{folder}: OK, complete and unmodified ({len(v.checked)} checks)")
        else:
            code = EXIT_FAIL
            _out(f"{folder}: NOT verified")
            for problem in v.problems:
                _out(f"  {problem}")
    return code


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2), already printed
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    try:
        code: int = args.func(args)
    except ConfigErrors as exc:
        for e in exc.errors:
            _err(e.location_message())
        return EXIT_USAGE
    except ConfigError as exc:
        _err(exc.location_message())
        return EXIT_USAGE
    except SupervisorError as exc:
        _err(f"supervisor: {exc}")
        return EXIT_FAIL
    except KeyboardInterrupt:
        return EXIT_OK
    except BrokenPipeError:
        return _stdout_closed()
    return code


EXIT_PIPE: Final = 128 + signal.SIGPIPE
"""Stdout closed by its reader (``check recipes/*.yaml | head -1``): quietly, with the status
of a Unix tool stopped by SIGPIPE."""


def _stdout_closed() -> int:
    # What is still buffered for the closed pipe would raise again when Python flushes
    # stdout at exit: point it at /dev/null (the Python documentation's recipe).
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    return EXIT_PIPE


if __name__ == "__main__":
    sys.exit(main())
