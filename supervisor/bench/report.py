"""Benchmark figures collected into one table (``make bench`` → ``var/bench/results.*``).

Each benchmark keeps printing its own lines; one that measures a figure of issue 13's table
also calls :func:`record`, which appends one JSON line to the file named by
``$SUPERVISOR_BENCH_RESULTS`` (nothing at all when it is unset: a benchmark run by hand
writes no file). ``supervisor bench report`` (:func:`write_report`) turns those lines into
``results.json`` and ``results.md``: figure | measured | target | reference | met?, with
the machine it ran on. A figure recorded twice keeps its last value (a re-run).

Every ``supervisor bench WHAT`` runs inside :func:`same_run_reference` (issue 30): the
figures it records carry the same run's reference, printed beside them, so that a figure
from one machine can be compared with another's: the share of the CPUs' time the
hypervisor took while it ran (``/proc/stat``'s steal) and :func:`reference_loop_s`, a
pure-Python loop of ten million additions timed once right after it. ``results.json``
keeps the loop timed by the report too, with the machine, and ``results.md`` ends with
issue 30's table (:data:`ISSUE30_ROWS`).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Final

__all__ = [
    "ENV",
    "ISSUE30_ROWS",
    "JITTER_UNCHANGED_MS",
    "REFERENCE_LOOP",
    "REFERENCE_LOOP_ADDITIONS",
    "CpuTicks",
    "Figure",
    "Issue30Row",
    "cpu_ticks",
    "issue30_table",
    "jitter_change",
    "machine",
    "met",
    "read",
    "record",
    "reference_loop_s",
    "same_run_reference",
    "same_run_text",
    "steal_share",
    "write_report",
]

ENV: Final = "SUPERVISOR_BENCH_RESULTS"
"""Environment variable naming the JSON-lines file that :func:`record` appends to."""


@dataclass(frozen=True, slots=True)
class Figure:
    figure: str
    """What is measured, as issue 13's table names it."""
    measured: float
    unit: str
    target: str
    """The target as written: ``"<= 0.3"``, ``">= 30000"``, ``"== 0"``."""
    reference: str
    """What it is compared with in the same run (the bare library, the run without load)."""
    command: str = ""
    """The command that measured it."""
    steal: float | None = None
    """The share of the CPUs' time (0-1) the hypervisor took while the benchmark ran
    (None: not known, or recorded outside :func:`same_run_reference`)."""
    loop_s: float | None = None
    """:func:`reference_loop_s` timed in the same run, right after the benchmark."""


_OPS: Final[dict[str, Callable[[float, float], bool]]] = {
    "<=": lambda a, b: a <= b,
    ">=": lambda a, b: a >= b,
    "==": lambda a, b: a == b,
    "<": lambda a, b: a < b,
    ">": lambda a, b: a > b,
}


JITTER_UNCHANGED_MS: Final = 0.1
"""How much the scan's start jitter p99 may rise with the extra load and still count as
"unchanged" (issue 13's HTTP/WebSocket row): a tenth of the 1 ms jitter target. The p99s
compared are 0.01-0.1 ms on a quiet scan, where a ratio of two of them swings by 2-20x
from run to run with the same code (docs/adr/0024-jitter-unchanged.md)."""


def jitter_change(alone_ms: float, loaded_ms: float) -> tuple[float, str]:
    """The rise of the start jitter p99 under load (ms; negative: it fell) and the
    reference line that shows both p99s and their ratio (for the record, not judged)."""
    ratio = f"{loaded_ms / alone_ms:.2f}x" if alone_ms > 0 else "n/a"
    return loaded_ms - alone_ms, (
        f"without {alone_ms:.3f} ms, with {loaded_ms:.3f} ms (ratio {ratio});"
        f" unchanged: a rise of at most {JITTER_UNCHANGED_MS:g} ms"
    )


@dataclass(frozen=True, slots=True)
class CpuTicks:
    """All CPUs' time so far, in clock ticks (``/proc/stat``'s ``cpu`` line): ``steal`` is
    the time the hypervisor gave this virtual machine's CPUs to others while they had work,
    ``total`` everything (user, nice, system, idle, iowait, irq, softirq, steal). A thread
    at a real-time priority cannot run while its CPU is stolen: what a benchmark's share of
    steal was tells the machine's noise from the code's (issue 13's jitter rows)."""

    steal: int
    total: int


def steal_share(spans: Iterable[tuple[CpuTicks, CpuTicks]]) -> float | None:
    """The share of the CPUs' time stolen over the spans (each a reading at its start and
    one at its end), 0 to 1; None when no tick passed in any."""
    stolen = total = 0
    for start, end in spans:
        stolen += end.steal - start.steal
        total += end.total - start.total
    return stolen / total if total > 0 else None


def cpu_ticks(stat_text: str | None = None) -> CpuTicks | None:
    """The machine's CPU ticks now (``stat_text``: the text of ``/proc/stat``, read when
    None); None where there is no such file or line (not Linux) or it has no steal
    column (a kernel older than 2.6.11)."""
    if stat_text is None:
        try:
            stat_text = Path("/proc/stat").read_text(encoding="ascii")
        except OSError:
            return None
    for line in stat_text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            # guest and guest_nice (fields 9-10) are already counted in user and nice.
            ticks = [int(x) for x in fields[1:9]]
            if len(ticks) < 8:
                return None
            return CpuTicks(steal=ticks[7], total=sum(ticks))
    return None


def met(measured: float, target: str) -> bool | None:
    """Whether ``measured`` meets ``target`` (``"<= 0.3"``); None for a target not in that
    form (it is shown, not judged)."""
    parts = target.split()
    if len(parts) < 2 or parts[0] not in _OPS:
        return None
    try:
        bound = float(parts[1].replace(",", "").replace("_", ""))
    except ValueError:
        return None
    return _OPS[parts[0]](measured, bound)


REFERENCE_LOOP_ADDITIONS: Final = 10_000_000
"""The pure-Python reference loop's additions (issue 30: 1.40 s on the machine where the
load case missed its targets)."""

REFERENCE_LOOP: Final = compile(
    f"s = 0\nfor i in range({REFERENCE_LOOP_ADDITIONS:_}):\n    s += i\n",
    "<reference loop>",
    "exec",
)
"""Issue 30's loop as it wrote it, at a module's top level: ``s`` and ``i`` are global
names, looked up in a dict at every addition. The same loop inside a function (local
names) runs about twice as fast and would not compare with the issue's 1.40 s."""


def reference_loop_s() -> float:
    """Wall seconds of ``for i in range(10_000_000): s += i`` at a module's top level in
    this interpreter, timed once: what one core of this machine gives pure Python now (its
    CPU, its clock, what else runs on it). A figure divided by its loop compares across
    machines."""
    names: dict[str, Any] = {}
    t0 = time.perf_counter()
    exec(REFERENCE_LOOP, names)  # our own constant code: the loop, nothing else
    took = time.perf_counter() - t0
    n = REFERENCE_LOOP_ADDITIONS
    if names["s"] != n * (n - 1) // 2:
        raise RuntimeError(f"the reference loop added up to {names['s']}")
    return took


def same_run_text(steal: float | None, loop_s: float | None) -> str:
    """The same run's reference in words: ``same run: hypervisor steal 0.12 % of the
    CPUs' time, 10M-addition loop 1.02 s`` (a part not known is said so)."""
    stolen = "steal not known" if steal is None else f"hypervisor steal {steal * 100:.2f} %"
    loop = "loop not timed" if loop_s is None else f"10M-addition loop {loop_s:.2f} s"
    return f"same run: {stolen} of the CPUs' time, {loop}"


@dataclass
class _Session:
    """The figures recorded while a benchmark runs, written when it ends with its
    reference (:func:`same_run_reference`)."""

    figures: list[Figure]


_session: _Session | None = None


def _write(fig: Figure) -> None:
    path = os.environ.get(ENV)
    if not path:
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with Path(path).open("a", encoding="utf-8") as f:
        f.write(json.dumps(asdict(fig), ensure_ascii=False) + "\n")


def record(
    figure: str, measured: float, unit: str, target: str, reference: str, command: str = ""
) -> None:
    """Append one figure to ``$SUPERVISOR_BENCH_RESULTS`` (no-op when it is unset); inside
    :func:`same_run_reference`, when the benchmark ends, with its same-run reference."""
    fig = Figure(figure, float(measured), unit, target, reference, command)
    if _session is not None:
        _session.figures.append(fig)
    else:
        _write(fig)


@contextmanager
def same_run_reference(
    say: Callable[[str], None], loop: Callable[[], float] = reference_loop_s
) -> Iterator[None]:
    """Run a benchmark with its same-run reference: the CPUs' ticks read before and after
    it (the steal share over its whole span), then the reference loop timed once; the
    reference said with ``say`` beside the benchmark's own lines and added to every figure
    it recorded, written then (also when it failed: what it measured stays)."""
    global _session
    outer, _session = _session, _Session([])
    before = cpu_ticks()
    try:
        yield
    finally:
        session = _session
        _session = outer
        assert session is not None
        after = cpu_ticks()
        steal = None if before is None or after is None else steal_share([(before, after)])
        # After the benchmark, never during it: the loop takes a core for about a second.
        loop_s = loop()
        say(f"  reference ({same_run_text(steal, loop_s)}; the loop timed after the benchmark)")
        for fig in session.figures:
            _write(replace(fig, steal=steal, loop_s=loop_s))


def read(path: Path) -> list[Figure]:
    """The figures of a JSON-lines file, the last of each name kept, in first-seen order."""
    by_name: dict[str, Figure] = {}
    if path.is_file():
        for raw in path.read_text(encoding="utf-8").splitlines():
            if raw.strip():
                fig = Figure(**json.loads(raw))
                by_name[fig.figure] = fig
    return list(by_name.values())


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """The machine the figures come from: CPU model, cores, Python, OS, and its load
    average when the table was written (a shared machine's other work shows in the scan's
    timing figures)."""
    return {
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "python": sys.version.split()[0],
        "implementation": platform.python_implementation(),
        "os": f"{platform.system()} {platform.release()}",
    }


def _fmt(x: float) -> str:
    if x == 0 or abs(x) >= 1000 or (x.is_integer() and abs(x) >= 10):
        return f"{x:,.0f}"
    if abs(x) >= 10:
        return f"{x:.1f}"
    return f"{x:.3g}"


def markdown(figures: list[Figure], host: dict[str, Any], when: str) -> str:
    lines = [
        f"Machine: {host['cpu']}, {host['cores']} cores, {host['implementation']}"
        f" {host['python']}, {host['os']}; {when}; load average (1, 5, 15 min)"
        f" {', '.join(str(x) for x in host['load_avg_1_5_15'])} when written"
        + (
            f"; the pure-Python reference loop (10M additions) {host['reference_loop_s']:.2f} s."
            if "reference_loop_s" in host
            else "."
        ),
        "",
        "| figure | measured | target | reference | met? |",
        "|---|---|---|---|---|",
    ]
    for f in figures:
        lines.append(_row(f.figure, f.measured, f.unit, f.target, _reference(f)))
    return "\n".join(lines) + "\n"


def _row(figure: str, measured: float | None, unit: str, target: str, reference: str) -> str:
    if measured is None:
        return f"| {figure} | not measured | {target} | {reference} | — |"
    ok = met(measured, target)
    mark = "—" if ok is None else ("yes" if ok else "**no**")
    unit = f" {unit}" if unit else ""
    return f"| {figure} | {_fmt(measured)}{unit} | {target} | {reference} | {mark} |"


def _reference(f: Figure) -> str:
    """The figure's own reference, then its same-run one when it was recorded."""
    if f.steal is None and f.loop_s is None:
        return f.reference
    same = same_run_text(f.steal, f.loop_s)
    return f"{f.reference}; {same}" if f.reference else same


def write_report(
    lines_file: Path, out_dir: Path, loop: Callable[[], float] = reference_loop_s
) -> tuple[Path, Path]:
    """``results.json`` and ``results.md`` in ``out_dir`` from the recorded figures: every
    figure, then issue 30's table; the machine with the reference loop timed now."""
    figures = read(lines_file)
    host = machine()
    host["reference_loop_s"] = round(loop(), 3)
    host["reference_loop"] = (
        f"for i in range({REFERENCE_LOOP_ADDITIONS:_}): s += i, timed once by the report;"
        " each figure keeps the one timed right after its own benchmark (loop_s)"
    )
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    out_dir.mkdir(parents=True, exist_ok=True)
    js, md = out_dir / "results.json", out_dir / "results.md"
    rows = issue30_table(figures)
    doc = {
        "machine": host,
        "when": when,
        "figures": [{**asdict(f), "met": met(f.measured, f.target)} for f in figures],
        "issue30": [asdict(r) for r in rows],
    }
    js.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    md.write_text(markdown(figures, host, when) + "\n" + issue30_markdown(rows), encoding="utf-8")
    return js, md


# --- issue 30's table --------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Issue30Row:
    """One row of issue 30's table as ``make bench`` filled it."""

    figure: str
    """The row as issue 30 names it."""
    measured: float | None
    """None: no benchmark of this run recorded it."""
    unit: str
    target: str
    reference: str
    met: bool | None
    source: str
    """The recorded figure it comes from ("" when none)."""


@dataclass(frozen=True, slots=True)
class _Issue30Spec:
    figure: str
    target: str
    unit: str
    match: tuple[str, ...]
    """Words that all appear in the name of the recorded figure it shows."""
    per_loop: bool = False
    """The figure times its run's reference loop (s), not the figure itself."""


DRY_RUN_ISSUE30_RATIO: Final = 22_474.0
DRY_RUN_ISSUE30_LOOP_S: Final = 1.40
DRY_RUN_BEFORE_ISOLATION: Final = DRY_RUN_ISSUE30_RATIO * DRY_RUN_ISSUE30_LOOP_S
"""The dry run's ratio times its machine's reference loop (s) before the isolation, as
issue 30 measured it: 22,474× with the loop at 1.40 s. The product is the dry run's speed
in units of the machine's pure-Python speed: a machine twice as fast doubles the ratio
and halves the loop."""

ISSUE30_ROWS: Final = (
    _Issue30Spec(
        "load case p99 scan duration / scan alone's p99, same run",
        "<= 1.2",
        "",
        ("scan alone's p99",),
    ),
    _Issue30Spec(
        "load case start jitter p99 − scan alone's, same run",
        "<= 0.2",
        "ms",
        ("start jitter p99 −", "scan alone's"),
    ),
    _Issue30Spec("load case overruns in the window", "== 0", "", ("overruns in", "(same load)")),
    _Issue30Spec(
        "load case p99/period at 10 ms", "<= 0.3", "", ("scan duration p99 / period (16 ch",)
    ),
    _Issue30Spec(
        "scan overruns while one OPC UA client browses 10,000 nodes in a loop and another"
        " polls GET /api/tags at 10/s",
        "== 0",
        "",
        ("browses 10,000 nodes", "overruns"),
    ),
    _Issue30Spec(
        "Chadèche bench CPU share of a Raspberry Pi 4 core (instructions/s converted)",
        "<= 10",
        "%",
        ("Raspberry Pi",),
    ),
    _Issue30Spec(
        "`supervisor check recipes/nimh-ds2710.yaml` wall time",
        "<= 0.3",
        "s",
        ("supervisor check", "wall time"),
    ),
    _Issue30Spec(
        "e-stop press → every output safe p99", "<= 25", "ms", ("e-stop press", "output safe")
    ),
    _Issue30Spec(
        "dry run of the 25 h recipe × the same run's reference loop (s): not lower after"
        " the isolation",
        f">= {DRY_RUN_BEFORE_ISOLATION:.0f}",
        "× s",
        ("dry run of", "nimh-25h-slow-cycle"),
        per_loop=True,
    ),
)
"""Issue 30's table, row by row: the target as the issue sets it and the recorded figure
that measures it. The dry run's row is derived: its ratio times the loop of its own run
(:data:`DRY_RUN_BEFORE_ISOLATION`)."""


def _issue30_row(spec: _Issue30Spec, figures: list[Figure]) -> Issue30Row:
    found = next((f for f in figures if all(w in f.figure for w in spec.match)), None)
    if found is None:
        return Issue30Row(spec.figure, None, spec.unit, spec.target, "", None, "")
    measured: float | None = found.measured
    reference = _reference(found)
    unit = found.unit or spec.unit
    if spec.per_loop:
        unit = spec.unit
        if found.loop_s is None:
            measured, reference = None, "its run timed no reference loop"
        else:
            measured = found.measured * found.loop_s
            reference = (
                f"{found.measured:,.0f}× with the loop at {found.loop_s:.2f} s (before the"
                f" isolation: {DRY_RUN_ISSUE30_RATIO:,.0f}× at {DRY_RUN_ISSUE30_LOOP_S:.2f} s);"
                f" {reference}"
            )
    ok = None if measured is None else met(measured, spec.target)
    return Issue30Row(spec.figure, measured, unit, spec.target, reference, ok, found.figure)


def issue30_table(figures: list[Figure]) -> list[Issue30Row]:
    """Issue 30's rows from the recorded figures; a row no benchmark recorded is kept,
    "not measured"."""
    return [_issue30_row(spec, figures) for spec in ISSUE30_ROWS]


def issue30_markdown(rows: list[Issue30Row]) -> str:
    lines = [
        "Issue 30 (this machine, this run):",
        "",
        "| figure | measured | target | same-run reference | met? |",
        "|---|---|---|---|---|",
    ]
    lines += [_row(r.figure, r.measured, r.unit, r.target, r.reference) for r in rows]
    return "\n".join(lines) + "\n"
