"""``supervisor bench pi-budget``: the four-Chadèche bench's CPU share of a Raspberry Pi 4 core.

Issue 30 asks for a budget that does not depend on the machine it is measured on. Wall or
CPU time does (this 2-core VM's speed moves by a third from hour to hour); the number of
CPU instructions a piece of work executes does not, so the figure is built from counts:

1. **Instructions per scan** of ``supervisor run`` on seed 000's bench: the four Chadèche
   boards of io_maps/sim.yaml (simulated, one NiMH cell each) with the settings of the
   Pi's own map io_maps/chadeche-rpi.yaml (100 ms scan, its poll and staleness periods),
   the historian, the OPC UA server and the HTTP server on (no client attached),
   benchmarks/load-cycle.yaml started on every channel (:func:`budget_map`). The process
   and those it starts (its OPC UA server's, ADR 0029) run under valgrind's callgrind with
   the counter off through the start-up; after a warm-up the counters are switched on
   (``callgrind_control -i on``), and after the window they are dumped (``callgrind_control
   -d``): the dumps hold the window's instructions, of every thread of every process,
   start-up excluded; the figure is their sum. The scans of the window are the scan counter of
   ``/api/diagnostics`` read on both sides of each switch (:func:`bracket`).
   Callgrind rather than cachegrind (which the dry-run figure uses, docs/performance.md):
   both count the same guest instructions (``Ir``), but only callgrind can be switched on
   and dumped from outside a running process.
2. **Instructions per second** at the bench's 100 ms scan: instructions per scan × 10.
3. **Share of a Raspberry Pi 4 core**: a Pi runs other instructions (AArch64) than this
   machine (x86-64), so instructions are not compared across machines; pure-Python
   workloads whose wall time on a Pi 4 is published are counted here instead, with this
   Python (:data:`PUBLISHED`): a published CPU benchmark's rounds (79.216 s for 10,000 on
   a Pi 4 under Ubuntu 22.04) and the N-body simulation (5,000,000 steps in 158.263 s on a
   Pi 4 at 1.5 GHz). A run's instructions here over its seconds there are how many *of
   this machine's Python instructions* a Pi 4 core runs a second (:func:`pi4_rate`); the
   lower of the two rates is used, so the share is the higher (:func:`pi4_share`). The
   sources, their confidence and what they leave out are in docs/performance.md ("A
   Raspberry Pi budget").

The reference printed beside the figure, from the same run: the pure-Python reference
loop (10 million additions) counted here and timed here, and what the conversion says it
would take on a Pi 4.

valgrind slows the process some fifty times: the scan can overrun its 100 ms period under
it, so the window's scans may be fewer than its wall seconds × 10 (both printed). The
figure is per scan, and the time-bound work (the servers' timers, the historian's flushes)
is then spread over fewer scans than on a Pi: the instructions per scan are, if anything,
over-counted.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import yaml

from supervisor.bench import report
from supervisor.bench.subject import Supervisor, prepare, recipe_args

log = logging.getLogger(__name__)

PI_MAP: Final = Path("io_maps/chadeche-rpi.yaml")
"""The Pi's own map (seed 000): its scan period and the Chadèche driver's periods."""
SIM_MAP: Final = Path("io_maps/sim.yaml")
"""Where the four simulated Chadèche boards and their channels are described."""
RECIPE: Final = Path("benchmarks/load-cycle.yaml")
"""A step change every 4–5 s on every channel: more chain work than a real 25 h recipe."""

VALGRIND: Final = "valgrind"
CALLGRIND_CONTROL: Final = "callgrind_control"


@dataclass(frozen=True, slots=True)
class PublishedRun:
    """A pure-Python workload whose wall time on a Raspberry Pi 4 is published: ``units``
    of its work (``run(units)`` of ``source``) took ``wall_s`` there."""

    name: str
    source: str
    units: int
    wall_s: float
    count_units: int
    """How many units are counted here (and twice as many: the difference is one unit's
    instructions times ``count_units``); valgrind runs some fifty times slower."""
    citation: str


REFERENCE_ADDITIONS: Final = report.REFERENCE_LOOP_ADDITIONS
"""The benchmarks' pure-Python reference loop: ten million additions (``report``)."""
REFERENCE_COUNT_UNITS: Final = 1_000_000
"""The reference loop's additions counted here (and twice as many)."""

REFERENCE_LOOP_SRC: Final = r"""
LOOP = "s = 0\nfor i in range(n):\n    s += i\n"

def run(n):
    # The loop as report.REFERENCE_LOOP runs it: module-level code, s and i global names.
    names = {"n": n}
    exec(LOOP, names)
    return names["s"]
"""
"""The reference loop as counted under valgrind, ``n`` additions a run; it is timed by
``report.reference_loop_s``."""

NBODY_SRC: Final = """
PI = 3.14159265358979323
SOLAR_MASS = 4 * PI * PI
DAYS_PER_YEAR = 365.24

def bodies():
    # The Sun and the four outer planets (positions in AU, velocities in AU/day, masses in
    # solar masses): the classic N-body benchmark's system.
    d, m = DAYS_PER_YEAR, SOLAR_MASS
    return [
        ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], m),
        ([4.84143144246472090e00, -1.16032004402742839e00, -1.03622044471123109e-01],
         [1.66007664274403694e-03 * d, 7.69901118419740425e-03 * d,
          -6.90460016972063023e-05 * d], 9.54791938424326609e-04 * m),
        ([8.34336671824457987e00, 4.12479856412430479e00, -4.03523417114321381e-01],
         [-2.76742510726862411e-03 * d, 4.99852801234917238e-03 * d,
          2.30417297573763929e-05 * d], 2.85885980666130812e-04 * m),
        ([1.28943695621391310e01, -1.51111514016986312e01, -2.23307578892655734e-01],
         [2.96460137564761618e-03 * d, 2.37847173959480950e-03 * d,
          -2.96589568540237556e-05 * d], 4.36624404335156298e-05 * m),
        ([1.53796971148509165e01, -2.59193146099879641e01, 1.79258772950371181e-01],
         [2.68067772490389322e-03 * d, 1.62824170038242295e-03 * d,
          -9.51592254519715870e-05 * d], 5.15138902046611451e-05 * m),
    ]

def run(n, dt=0.01):
    system = bodies()
    pairs = [(system[i], system[j]) for i in range(len(system)) for j in range(i + 1, len(system))]
    px = py = pz = 0.0
    for _, (vx, vy, vz), mass in system:
        px -= vx * mass
        py -= vy * mass
        pz -= vz * mass
    sun_v = system[0][1]
    sun_v[0], sun_v[1], sun_v[2] = px / SOLAR_MASS, py / SOLAR_MASS, pz / SOLAR_MASS
    for _ in range(n):
        for ((x1, y1, z1), v1, m1), ((x2, y2, z2), v2, m2) in pairs:
            dx, dy, dz = x1 - x2, y1 - y2, z1 - z2
            mag = dt * ((dx * dx + dy * dy + dz * dz) ** (-1.5))
            b1m, b2m = m1 * mag, m2 * mag
            v1[0] -= dx * b2m
            v1[1] -= dy * b2m
            v1[2] -= dz * b2m
            v2[0] += dx * b1m
            v2[1] += dy * b1m
            v2[2] += dz * b1m
        for r, (vx, vy, vz), _ in system:
            r[0] += dt * vx
            r[1] += dt * vy
            r[2] += dt * vz
    return system[1][0][0]
"""
"""The N-body simulation of the published Pi 4 figure (the classic benchmark's algorithm:
five bodies, ten pairs, a 0.01-day step), written here."""

PI_BENCH_SRC: Final = '''
# The rounds of a published single-core Python CPU benchmark, run as module-level code as
# there (its loop variables are globals): per round, 999 powers of two times pi and twice
# 9,999 float divisions, their results dropped.
ROUNDS = """
for i in range(0, rounds):
    for x in range(1, 1000):
        3.141592 * 2**x
    for x in range(1, 10000):
        float(x) / 3.141592
    for x in range(1, 10000):
        float(3.141592) / x
"""

def run(rounds):
    exec(ROUNDS, {"rounds": rounds})
'''
"""The workload of alexdedyura/cpu-benchmark as it was when its Raspberry Pi 4 result was
published (the file at commit af8c011, 2023-12-18; result added 2024-01-12), written here."""

NBODY: Final = PublishedRun(
    name="N-body",
    source=NBODY_SRC,
    units=5_000_000,
    wall_s=158.263,
    count_units=20_000,
    citation="C. Mehta, Performance Analysis of Languages on Raspberry Pi (2020-01-28): Python"
    " N-body, 5,000,000 steps in 158.263 s, Pi 4 B Rev 1.1 at 1.5 GHz, performance governor",
)
PI_BENCH: Final = PublishedRun(
    name="cpu-benchmark",
    source=PI_BENCH_SRC,
    units=10_000,
    wall_s=79.216,
    count_units=2,
    citation="A. Dedyura, cpu-benchmark README (2024-01-12): Raspberry Pi 4, Ubuntu 22.04.3"
    " (Python 3.10), 79.216 s a 10,000-round attempt, mean of 10",
)
PUBLISHED: Final = (PI_BENCH, NBODY)
"""The Pi 4's rate is the lower of the two: the share is then the higher (conservative)."""

WARMUP_S: Final = 20.0
STALE_UNDER_VALGRIND_S: Final = 20.0
RUNNING_TIMEOUT_S: Final = 300.0
"""How long the recipes may take to be Running on every channel after the warm-up."""
START_TIMEOUT_S: Final = 900.0
"""valgrind makes the start-up (imports, the servers) minutes long on a loaded machine."""


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


# --- arithmetic (tests/unit/test_pibudget.py) ------------------------------------------------


_TOTALS = re.compile(r"^(?:totals|summary):\s*(\d+)", re.MULTILINE)


def callgrind_total(text: str) -> int:
    """The instructions (``Ir``, the first event) of a callgrind output file: its
    ``totals:`` line, or ``summary:`` where an older valgrind writes only that."""
    found: dict[str, int] = {}
    for line in text.splitlines():
        m = _TOTALS.match(line)
        if m:
            found[line.split(":", 1)[0]] = int(m.group(1))
    for key in ("totals", "summary"):
        if key in found:
            return found[key]
    raise ValueError("no totals: or summary: line in the callgrind output")


def per_unit(count_small: int, count_big: int, units_small: int, units_big: int) -> float:
    """Instructions per unit of work from two runs of ``units_small`` and ``units_big``
    units: the difference cancels what both runs do once (interpreter start-up, imports,
    exit)."""
    if units_big <= units_small:
        raise ValueError("the bigger run must do more units of work")
    return (count_big - count_small) / (units_big - units_small)


def pi4_rate(instructions_per_unit: float, run: PublishedRun) -> float:
    """How many of this machine's Python instructions a Pi 4 core runs a second: a
    published run's work (its units, counted here) over its published seconds."""
    if run.wall_s <= 0 or run.units <= 0:
        raise ValueError("a published run has units and seconds > 0")
    return instructions_per_unit * run.units / run.wall_s


def pi4_share(instructions_per_s: float, rate_per_s: float) -> float:
    """The share (0..1 and beyond) of one Pi 4 core that ``instructions_per_s`` takes."""
    if rate_per_s <= 0:
        raise ValueError("the Pi 4 rate must be > 0")
    return instructions_per_s / rate_per_s


@dataclass(frozen=True, slots=True)
class Bracket:
    """A counter read just before and just after an event whose own time is unknown."""

    before: float
    after: float

    @property
    def mid(self) -> float:
        return (self.before + self.after) / 2

    @property
    def half_width(self) -> float:
        return (self.after - self.before) / 2


def window_scans(start: Bracket, end: Bracket) -> tuple[float, float]:
    """The scans between two switches of the counter, each bracketed by two readings of
    the scan counter: the difference of the midpoints, and how far off it can be."""
    return end.mid - start.mid, start.half_width + end.half_width


def bracket(read: Callable[[], float], event: Callable[[], object]) -> Bracket:
    before = read()
    event()
    return Bracket(before, read())


# --- the bench -------------------------------------------------------------------------------


def budget_map(pi_map: Path = PI_MAP, sim_map: Path = SIM_MAP) -> dict[str, Any]:
    """Seed 000's bench as a Pi runs it, simulated: ``pi_map`` (scan, driver periods, HMI)
    with the four Chadèche boards and their channels of ``sim_map`` on the simulated SPI
    backend, the historian and OPC UA on. Two settings differ from the Pi's, for valgrind
    and not for the count: the scan's real-time priority is dropped (valgrind's threads
    take turns on one lock: a SCHED_FIFO thread spinning before each scan would hold the
    others off the CPU), and the inputs go stale after :data:`STALE_UNDER_VALGRIND_S`
    rather than 2 s (valgrind's start-up and a loaded machine hold the loop for seconds;
    the channels tripped on stale inputs and held, and a held channel's chain does no
    work: a count of a bench that is not testing)."""
    pi: dict[str, Any] = yaml.safe_load(pi_map.read_text(encoding="utf-8"))
    sim: dict[str, Any] = yaml.safe_load(sim_map.read_text(encoding="utf-8"))
    chadeche = dict(pi["devices"]["chadeche"])
    chadeche.pop("spi", None)
    chadeche["backend"] = "sim"
    chadeche["stale_after_s"] = max(float(chadeche["stale_after_s"]), STALE_UNDER_VALGRIND_S)
    chadeche["boards"] = sim["devices"]["chadeche"]["boards"]
    channels = [c for c in sim["channels"] if c["source"]["device"] == "chadeche"]
    scan = {k: v for k, v in pi["scan"].items() if k != "realtime_priority"}
    return {
        "bench": "pi_budget",
        "description": "Seed 000: four Chadèche boards (simulated) as on the Raspberry Pi",
        "scan": scan,
        "hmi": dict(pi.get("hmi") or {}),
        "opcua": {"enabled": True, "host": "127.0.0.1", "port": 4840},
        "history": {"enabled": True},
        "state_dir": "var/pi-budget",
        "devices": {"chadeche": chadeche},
        "channels": channels,
    }


def _valgrind(out_file: Path, instr_at_start: bool, children: bool = False) -> list[str]:
    """valgrind's callgrind command prefix; ``children``: every process the command starts
    runs under it too (the OPC UA server's process, ADR 0029), each writing
    ``out_file.<pid>``."""
    exe = shutil.which(VALGRIND)
    if exe is None:
        raise RuntimeError(
            "valgrind is missing: `make valgrind` installs Debian's valgrind"
            " (apt-get install valgrind)"
        )
    out = f"{out_file}.%p" if children else str(out_file)
    return [
        exe,
        "--tool=callgrind",
        f"--callgrind-out-file={out}",
        f"--instr-atstart={'yes' if instr_at_start else 'no'}",
        "--dump-line=no",  # the totals only: no per-line tables to write at each dump
        *(["--trace-children=yes"] if children else []),
    ]


def children_of(pid: int, proc: Path = Path("/proc")) -> list[int]:
    """The processes whose parent is ``pid`` (``/proc/<pid>/stat``'s fourth field)."""
    found = []
    for stat in proc.glob("[0-9]*/stat"):
        try:
            text = stat.read_text(encoding="utf-8", errors="replace")
        except OSError:  # gone meanwhile
            continue
        # "pid (comm) state ppid ...": the name may hold spaces and parentheses.
        fields = text[text.rfind(")") + 2 :].split()
        if len(fields) > 1 and int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return sorted(found)


def _env() -> dict[str, str]:
    # The same hash seed every run: set and dict layouts (and so the instructions) do not
    # move with a random seed.
    return {**os.environ, "PYTHONHASHSEED": "0"}


SEGMENT_MARK: Final = "time_sleep"
"""The C function of ``time.sleep``: callgrind dumps its counter before each call
(``--dump-before``), so ``time.sleep(0)`` between two pieces of a script cuts the count."""


def segments_script(workloads: list[tuple[str, int]]) -> str:
    """A script that runs each ``(source, units)`` for ``units`` then ``2 * units``, with
    ``time.sleep(0)`` before the first run and after every run: its dumps are the start-up,
    then the runs in that order."""
    lines = ["import time", "time.sleep(0)"]
    for k, (source, units) in enumerate(workloads):
        lines.append(f"w{k} = {{}}")
        lines.append(f"exec({source!r}, w{k})")
        lines.append(f"w{k}['run']({units})")
        lines.append("time.sleep(0)")
        lines.append(f"w{k}['run']({2 * units})")
        lines.append("time.sleep(0)")
    return "\n".join(lines) + "\n"


def per_unit_of_segments(segments: list[int], workloads: list[tuple[str, int]]) -> list[float]:
    """Instructions per unit of each workload from the dumps of :func:`segments_script`
    (the start-up first): its run of ``2 * units`` less its run of ``units``. The segments
    hold the code around the runs too (the ``exec`` of the next source, a call): the
    difference cancels what both runs do once."""
    if len(segments) != 1 + 2 * len(workloads):
        raise ValueError(f"{len(segments)} dumps for {len(workloads)} workloads")
    return [
        per_unit(segments[1 + 2 * k], segments[2 + 2 * k], units, 2 * units)
        for k, (_, units) in enumerate(workloads)
    ]


def count_per_unit(workloads: list[tuple[str, int]], tmp: Path) -> list[float]:
    """Instructions per unit of each ``(source, units)`` (a ``run(units)`` function), all
    counted in one process under callgrind: one interpreter start-up, not two a workload."""
    out = tmp / "workloads.out"
    cmd = [
        *_valgrind(out, True),
        f"--dump-before={SEGMENT_MARK}",
        sys.executable,
        "-c",
        segments_script(workloads),
    ]
    subprocess.run(cmd, check=True, env=_env(), capture_output=True)
    dumps = sorted(tmp.glob("workloads.out.*"), key=lambda p: int(p.suffix[1:]))
    segments = [callgrind_total(p.read_text(encoding="utf-8", errors="replace")) for p in dumps]
    return per_unit_of_segments(segments, workloads)


@dataclass(frozen=True, slots=True)
class Window:
    instructions: int
    scans: float
    scans_error: float
    wall_s: float
    overruns: float
    chains_running: int
    channels: int
    processes: list[int] = field(default_factory=list)
    """The window's instructions by process: the supervisor's first, then its children's."""


def _control_all(pids: list[int], *args: str) -> None:
    """``callgrind_control ARGS PID`` for every process at once: one after the other, the
    switches of four processes took seconds (each reaches its process through vgdb), and
    the scans counted around them were that much less certain."""
    exe = shutil.which(CALLGRIND_CONTROL)
    if exe is None:
        raise RuntimeError("callgrind_control is missing (it comes with valgrind)")
    procs = [
        subprocess.Popen([exe, *args, str(pid)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        for pid in pids
    ]
    for pid, proc in zip(pids, procs, strict=True):
        _, err = proc.communicate(timeout=300)
        if proc.returncode != 0:
            raise RuntimeError(f"callgrind_control {' '.join(args)} {pid}: {err.decode()}")


def _chains_running(sup: Supervisor) -> int:
    tags = sup.get("/api/tags", timeout_s=60.0)
    rows = tags["tags"] if isinstance(tags, dict) else tags
    return sum(
        1
        for t in rows
        if str(t.get("name", "")).endswith(".chain.state") and t.get("value") == "Running"
    )


def _wait_running(sup: Supervisor, channels: int) -> None:
    """Until every channel's chain is Running (``--start`` starts them once the inputs
    read GOOD); an error if that does not come: the window would count a bench at rest."""
    deadline = time.monotonic() + RUNNING_TIMEOUT_S
    while (running := _chains_running(sup)) < channels:
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"{running} of {channels} step chains Running after {RUNNING_TIMEOUT_S:g} s:"
                f" no window counted ({sup.tail()})"
            )
        time.sleep(1.0)


def _window_counts(root: Path, pids: list[int], sup: Supervisor) -> list[int]:
    """Each process's instructions in the window: its first dump (``callgrind.out.PID.1``)."""
    counts = []
    for pid in pids:
        dump = root / f"callgrind.out.{pid}.1"
        if not dump.is_file():
            raise RuntimeError(f"callgrind wrote no dump for process {pid}: {sup.tail()}")
        counts.append(callgrind_total(dump.read_text(encoding="utf-8", errors="replace")))
    return counts


def measure_window(window_s: float, warmup_s: float, root: Path) -> Window:
    """Run the budget's bench under callgrind; the instructions and scans of a window of
    ``window_s`` wall seconds after ``warmup_s`` seconds of scanning."""
    cfg = budget_map()
    source = root / "pi-budget.yaml"
    source.write_text(yaml.safe_dump(cfg, allow_unicode=True, sort_keys=False), encoding="utf-8")
    copy, http_port, _ = prepare(source, root)
    channels = [c["name"] for c in cfg["channels"]]
    out = root / "callgrind.out"
    sup = Supervisor(
        copy,
        http_port,
        recipe_args(channels, RECIPE),
        root / "run.log",
        env=_env(),
        prefix=_valgrind(out, instr_at_start=False, children=True),
    )
    try:
        sup.wait_ready(START_TIMEOUT_S)
        time.sleep(warmup_s)
        _wait_running(sup, len(channels))

        def scans() -> float:
            return float(sup.get("/api/diagnostics", timeout_s=60.0)["scan"]["count"])

        overruns0 = float(sup.get("/api/diagnostics", timeout_s=60.0)["scan"]["overruns"])
        # The supervisor and the processes it started (its OPC UA server): a Pi runs them all.
        pids = [sup.pid, *children_of(sup.pid)]
        t0 = time.monotonic()
        start = bracket(scans, lambda: _control_all(pids, "-i", "on"))
        time.sleep(window_s)
        end = bracket(scans, lambda: _control_all(pids, "-d"))
        wall_s = time.monotonic() - t0
        diag = sup.get("/api/diagnostics", timeout_s=60.0)
        running = _chains_running(sup)
        if children_of(sup.pid) != pids[1:]:
            raise RuntimeError(
                f"the supervisor's processes changed during the window ({pids[1:]} before,"
                f" {children_of(sup.pid)} after: a restart?): no figure"
            )
    finally:
        code = sup.stop()
        if code != 0:
            _say(f"  supervisor run exited with {code}: {sup.tail()}")
    counts = _window_counts(root, pids, sup)
    n, err = window_scans(start, end)
    return Window(
        instructions=sum(counts),
        scans=n,
        scans_error=err,
        wall_s=wall_s,
        overruns=float(diag["scan"]["overruns"]) - overruns0,
        chains_running=running,
        channels=len(channels),
        processes=counts,
    )


@dataclass(frozen=True, slots=True)
class Budget:
    per_scan: float
    per_s: float
    rates: dict[str, float]
    """A Pi 4 core's instructions a second by each published run (this machine's kind)."""
    rate: float
    """The lowest of ``rates``: the one the share is computed with."""
    share: float


def budget(w: Window, period_s: float, per_unit_here: dict[str, float]) -> Budget:
    """The figures of a window: instructions per scan, per second at the scan's period,
    and the share of a Pi 4 core by the published runs (``per_unit_here``: the
    instructions of one unit of each, counted here, by name)."""
    if w.scans <= 0:
        raise ValueError("no scan in the window")
    per_scan = w.instructions / w.scans
    per_s = per_scan / period_s
    rates = {run.name: pi4_rate(per_unit_here[run.name], run) for run in PUBLISHED}
    rate = min(rates.values())
    return Budget(per_scan, per_s, rates, rate, pi4_share(per_s, rate))


def count_references(root: Path, count_scale: float = 1.0) -> tuple[float, dict[str, float]]:
    """Instructions of one addition of the reference loop and of one unit of each published
    run (by name), counted here. ``count_scale`` shrinks the counted runs (a test's quick
    pass: a unit costs the same instructions in a shorter run)."""
    workloads = [(REFERENCE_LOOP_SRC, REFERENCE_COUNT_UNITS)]
    workloads += [(run.source, run.count_units) for run in PUBLISHED]
    counted = count_per_unit(
        [(src, max(1, round(units * count_scale))) for src, units in workloads], root
    )
    return counted[0], {run.name: n for run, n in zip(PUBLISHED, counted[1:], strict=True)}


def _print_budget(w: Window, b: Budget, here: dict[str, float], period_s: float) -> None:
    _say(
        f"pi budget: supervisor run, seed 000's four Chadèche boards (simulated), scan"
        f" {period_s * 1000:g} ms, history + OPC UA + HTTP on (no client), {RECIPE} on all"
        f" {w.channels} channels ({w.chains_running} Running at the end)"
    )
    _say(
        f"  window: {w.instructions:,} instructions (callgrind) in {w.scans:.0f} ±"
        f" {w.scans_error:.1f} scans, {w.wall_s:.0f} s wall under valgrind"
        f" ({w.scans / w.wall_s:.1f} scans/s, {w.overruns:.0f} overruns)"
    )
    if len(w.processes) > 1:
        _say(
            f"  by process: the supervisor {w.processes[0]:,}, the processes it started"
            f" (its OPC UA server, the recipe checks' workers)"
            f" {', '.join(f'{n:,}' for n in w.processes[1:])}"
        )
    _say(f"  {b.per_scan:,.0f} instructions per scan, {b.per_s:,.0f} per second at the scan")
    for run in PUBLISHED:
        _say(
            f"  Pi 4 core by {run.name}: {b.rates[run.name]:,.0f} instructions/s"
            f" ({here[run.name]:,.0f} a unit here; {run.citation})"
        )
    _say(f"  share of one Raspberry Pi 4 core: {b.share * 100:.2f} % (target ≤ 10 %)")


def pi_budget_benchmark(
    window_s: float = 60.0, warmup_s: float = WARMUP_S, count_scale: float = 1.0
) -> int:
    """``supervisor bench pi-budget``: print (and record) the figure and its references
    (``count_scale``: :func:`count_references`)."""
    period_s = float(budget_map()["scan"]["period_s"])
    with tempfile.TemporaryDirectory(prefix="bench-pi-budget-") as tmp:
        root = Path(tmp)
        t0 = time.monotonic()
        w = measure_window(window_s, warmup_s, root)
        t1 = time.monotonic()
        loop_wall_s = report.reference_loop_s()
        loop_per_addition, here = count_references(root, count_scale)
        log.info(
            "pi budget: the window's run took %.0f s, the references' counts %.0f s",
            t1 - t0,
            time.monotonic() - t1,
        )
    b = budget(w, period_s, here)
    _print_budget(w, b, here, period_s)
    if w.chains_running < w.channels:
        _say("  a chain stopped during the window (see the log above): no figure recorded")
        return 1
    loop_instructions = loop_per_addition * REFERENCE_ADDITIONS
    pi_loop_s = loop_instructions / b.rate
    _say(
        f"  reference: the pure-Python loop of {REFERENCE_ADDITIONS:,} additions,"
        f" {loop_instructions:,.0f} instructions, {loop_wall_s:.2f} s here,"
        f" {pi_loop_s:.2f} s on a Pi 4 by the conversion"
    )
    report.record(
        "Chadèche bench CPU share of a Raspberry Pi 4 core (instructions/s converted)",
        b.share * 100,
        "%",
        "<= 10",
        f"{b.per_scan:,.0f} instructions/scan, {b.per_s:,.0f}/s at {period_s * 1000:g} ms;"
        f" a Pi 4 core {b.rate:,.0f}/s (the lower of "
        + ", ".join(f"{n} {r:,.0f}/s" for n, r in b.rates.items())
        + f"); reference loop {loop_wall_s:.2f} s here, {pi_loop_s:.2f} s on a Pi 4 by the"
        " same conversion",
        f"supervisor bench pi-budget --seconds {window_s:g}",
    )
    return 0
