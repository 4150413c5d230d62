"""``supervisor bench cli``: how long the command line takes to check a recipe (issue 30).

Most of a short command's wall time is the interpreter starting and the imports before the
file is read; a machine twice as slow takes twice as long for both. So each run of the
command is timed beside the same run's references: the interpreter's own start
(``python -c pass``) and the package's (``python -c "import supervisor"``), each a fresh
process, the three interleaved round after round (what else the machine does falls on all
of them alike). The figure is the median of the runs; the references are printed and
recorded beside it.

The commands run with their bytecode cached (``__pycache__``, written by an untimed first
round even where ``PYTHONDONTWRITEBYTECODE`` is set): what an installed package has (its
installer compiles it) and what any second run of a checkout has. Without it every module
of the package is compiled from source at each start, which is not the command's time.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from supervisor.bench import report

CLI_RECIPE: Final = "recipes/nimh-ds2710.yaml"
"""The file the issue's figure checks."""

CHECK_TARGET_S: Final = 0.3
"""Issue 30: ``supervisor check recipes/nimh-ds2710.yaml`` in at most 0.3 s wall."""

# What the console script ``supervisor`` runs (pyproject's [project.scripts]), with the
# interpreter running this benchmark: the one whose start is the reference.
_MAIN: Final = "import sys; from supervisor.cli.main import main; sys.exit(main())"


@dataclass(frozen=True, slots=True)
class Timed:
    """One command's wall times and CPU times (user + system), seconds, a fresh process
    each run. The CPU time moves less than the wall time with what else the machine does
    (a process waiting for a CPU spends wall time, not CPU time): printed beside it."""

    label: str
    argv: tuple[str, ...]
    walls_s: tuple[float, ...]
    cpus_s: tuple[float, ...]

    @property
    def median_s(self) -> float:
        return statistics.median(self.walls_s)

    @property
    def cpu_median_s(self) -> float:
        return statistics.median(self.cpus_s)

    def line(self) -> str:
        return (
            f"  {self.label:<48} median {self.median_s * 1000:7.1f} ms"
            f"  (min–max {min(self.walls_s) * 1000:.1f}–{max(self.walls_s) * 1000:.1f} ms)"
            f"  CPU {self.cpu_median_s * 1000:.1f} ms"
        )


def _environment() -> dict[str, str]:
    """This process's environment, the bytecode written (see the module's docstring)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _children_cpu_s() -> float:
    """User + system time of this process's children that have ended, seconds."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _run_s(argv: Sequence[str], env: dict[str, str]) -> tuple[float, float]:
    """Wall and CPU time of one run; a run that fails stops the benchmark (it would time an
    error)."""
    cpu0 = _children_cpu_s()
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=False, env=env)
    wall = time.perf_counter() - t0
    cpu = _children_cpu_s() - cpu0
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(argv)}: exit {done.returncode}: {done.stderr.strip() or done.stdout}"
        )
    return wall, cpu


def time_commands(commands: dict[str, Sequence[str]], runs: int) -> list[Timed]:
    """Each command run ``runs`` times, round after round (one run of each per round), after
    one untimed round (the files into the page cache and their bytecode written, as on any
    second run)."""
    env = _environment()
    for argv in commands.values():
        _run_s(argv, env)
    times: dict[str, list[tuple[float, float]]] = {label: [] for label in commands}
    for _ in range(runs):
        for label, argv in commands.items():
            times[label].append(_run_s(argv, env))
    return [
        Timed(
            label,
            tuple(commands[label]),
            tuple(wall for wall, _ in runs_of),
            tuple(cpu for _, cpu in runs_of),
        )
        for label, runs_of in times.items()
    ]


def cli_commands(python: str = sys.executable) -> dict[str, Sequence[str]]:
    """The timed commands, references first: the figure's, then two more checks shown."""
    return {
        "python -c pass": (python, "-c", "pass"),
        'python -c "import supervisor"': (python, "-c", "import supervisor"),
        f"supervisor check {CLI_RECIPE}": (python, "-c", _MAIN, "check", CLI_RECIPE),
        "supervisor check io_maps/sim.yaml": (python, "-c", _MAIN, "check", "io_maps/sim.yaml"),
        "supervisor --help": (python, "-c", _MAIN, "--help"),
    }


def cli_benchmark(runs: int) -> int:
    """Print the median wall time of ``runs`` runs of each command; record the figure."""
    commands = cli_commands()
    timed = {t.label: t for t in time_commands(commands, runs)}
    sys.stdout.write(
        f"cli benchmark: median of {runs} runs, a fresh process each, bytecode cached\n"
    )
    for t in timed.values():
        sys.stdout.write(t.line() + "\n")
    bare, package = timed["python -c pass"], timed['python -c "import supervisor"']
    check = timed[f"supervisor check {CLI_RECIPE}"]
    beyond_ms = (check.median_s - bare.median_s) * 1000
    sys.stdout.write(
        f"  the check takes {beyond_ms:.1f} ms beyond the interpreter's start"
        f" (target: the check ≤ {CHECK_TARGET_S * 1000:.0f} ms)\n"
    )
    sys.stdout.flush()
    report.record(
        f"`supervisor check {CLI_RECIPE}` wall time",
        check.median_s,
        "s",
        f"<= {CHECK_TARGET_S}",
        f"same run: interpreter start (python -c pass) {bare.median_s * 1000:.1f} ms,"
        f" python -c 'import supervisor' {package.median_s * 1000:.1f} ms; median of {runs}"
        f" runs, min–max {min(check.walls_s) * 1000:.0f}–{max(check.walls_s) * 1000:.0f} ms;"
        f" CPU {check.cpu_median_s * 1000:.0f} ms (python -c pass"
        f" {bare.cpu_median_s * 1000:.0f} ms)",
        f"supervisor bench cli --runs {runs}",
    )
    return 0
