"""Benchmark figures collected into one table (``make bench`` → ``var/bench/results.*``).

Each benchmark keeps printing its own lines; one that measures a figure of issue 13's table
also calls :func:`record`, which appends one JSON line to the file named by
``$SUPERVISOR_BENCH_RESULTS`` (nothing at all when it is unset: a benchmark run by hand
writes no file). ``supervisor bench report`` (:func:`write_report`) turns those lines into
``results.json`` and ``results.md``: figure | measured | target | reference | met?, with
the machine it ran on. A figure recorded twice keeps its last value (a re-run).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final

__all__ = [
    "ENV",
    "JITTER_UNCHANGED_MS",
    "CpuTicks",
    "Figure",
    "cpu_ticks",
    "jitter_change",
    "machine",
    "met",
    "read",
    "record",
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


def record(
    figure: str, measured: float, unit: str, target: str, reference: str, command: str = ""
) -> None:
    """Append one figure to ``$SUPERVISOR_BENCH_RESULTS`` (no-op when it is unset)."""
    path = os.environ.get(ENV)
    if not path:
        return
    line = json.dumps(asdict(Figure(figure, float(measured), unit, target, reference, command)))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with Path(path).open("a", encoding="utf-8") as f:
        f.write(line + "\n")


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
        f" {', '.join(str(x) for x in host['load_avg_1_5_15'])} when written.",
        "",
        "| figure | measured | target | reference | met? |",
        "|---|---|---|---|---|",
    ]
    for f in figures:
        ok = met(f.measured, f.target)
        mark = "—" if ok is None else ("yes" if ok else "**no**")
        unit = f" {f.unit}" if f.unit else ""
        lines.append(
            f"| {f.figure} | {_fmt(f.measured)}{unit} | {f.target} | {f.reference} | {mark} |"
        )
    return "\n".join(lines) + "\n"


def write_report(lines_file: Path, out_dir: Path) -> tuple[Path, Path]:
    """``results.json`` and ``results.md`` in ``out_dir`` from the recorded figures."""
    figures = read(lines_file)
    host = machine()
    when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    out_dir.mkdir(parents=True, exist_ok=True)
    js, md = out_dir / "results.json", out_dir / "results.md"
    doc = {
        "machine": host,
        "when": when,
        "figures": [{**asdict(f), "met": met(f.measured, f.target)} for f in figures],
    }
    js.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    md.write_text(markdown(figures, host, when), encoding="utf-8")
    return js, md
