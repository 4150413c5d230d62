"""``supervisor bench WHAT``: the benchmark each ``WHAT`` names, run with the command line's
arguments (the command line parses them and sets logging; ``supervisor.cli.main``)."""

from __future__ import annotations

import argparse
import asyncio
import functools
import logging
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

from supervisor.bench import report as same_run


def _out(msg: str) -> None:
    sys.stdout.write(msg.rstrip("\n") + "\n")
    sys.stdout.flush()


def _with_reference(
    run: Callable[[argparse.Namespace, Path], int],
) -> Callable[[argparse.Namespace, Path], int]:
    """Each benchmark followed by its same-run reference (issue 30: the hypervisor's steal
    while it ran, the pure-Python reference loop), printed and kept with its figures; the
    report times its own loop."""

    @functools.wraps(run)
    def with_reference(args: argparse.Namespace, default_io_map: Path) -> int:
        if args.what == "report":
            return run(args, default_io_map)
        with same_run.same_run_reference(_out):
            return run(args, default_io_map)

    return with_reference


@_with_reference
def run_bench(args: argparse.Namespace, default_io_map: Path) -> int:
    """Run the benchmark ``args.what`` names; its exit code. ``default_io_map``: the bench
    of those that run on the simulated seed 002 bench (``seed002``, ``estop``)."""
    from supervisor.bench import benchmarks

    tags = _tags(args, 1000)
    if args.what == "scan":
        return asyncio.run(
            benchmarks.scan_benchmark(
                tags,
                args.period_ms / 1000,
                args.seconds,
                recipes=args.recipes,
                settle=not args.no_settle,
            )
        )
    if args.what == "historian":
        return asyncio.run(
            benchmarks.historian_benchmark(tags, args.period_ms / 1000, args.seconds)
        )
    if args.what == "seed002":
        return asyncio.run(benchmarks.seed002_benchmark(str(default_io_map)))
    if args.what == "faults":
        from supervisor.bench import faults

        for line in faults.table(asyncio.run(faults.run_all())):
            _out(line)
        return 0
    if args.what == "estop":
        logging.disable(logging.ERROR)  # every press trips the channel, logged at ERROR
        return asyncio.run(
            benchmarks.estop_benchmark(str(default_io_map), args.presses, args.period_ms / 1000)
        )
    if args.what == "kill-restart":
        from supervisor.bench.killrestart import kill_restart_benchmark

        return kill_restart_benchmark(args.iterations, args.seed)
    if args.what == "influx":
        from supervisor.bench.influx import influx_benchmark

        return influx_benchmark(args.points, args.rounds)
    if args.what == "http":
        from supervisor.bench.http import http_benchmark

        return asyncio.run(
            http_benchmark(
                tags, args.period_ms / 1000, args.seconds, args.http_clients, args.ws_clients
            )
        )
    if args.what == "opcua":
        return asyncio.run(
            benchmarks.opcua_benchmark(
                args.clients, args.seconds, args.opcua_tags, args.period_ms / 1000
            )
        )
    if args.what == "flood":
        from supervisor.bench.flood import flood_benchmark

        return flood_benchmark(
            args.flood_http, args.flood_opcua, args.login_rate, args.login_seconds
        )
    if args.what == "validate-attack":
        from supervisor.bench.validate import validate_attack_benchmark

        return validate_attack_benchmark()
    if args.what in _BY_NAME:
        return _BY_NAME[args.what](args)
    if args.what in ("load", "memory", "pi-budget", "report"):
        from supervisor.bench import suite

        return suite.run(args)
    if args.what == "dry-run":
        return _dry_run(args)
    return asyncio.run(benchmarks.manual_charge_benchmark(args.hours))


def _tags(args: argparse.Namespace, default: int) -> int:
    """``--tags``, or the benchmark's own default (a bench of the fleet has 100, the scan's
    and the historian's load 1000)."""
    given = getattr(args, "tags", None)  # a namespace built by hand may have none
    return default if given is None else int(given)


def _cli(args: argparse.Namespace) -> int:
    from supervisor.bench.cli import cli_benchmark

    return cli_benchmark(args.runs)


def _fleet(args: argparse.Namespace) -> int:
    from supervisor.bench.fleet import fleet_benchmark

    return fleet_benchmark(args.benches, _tags(args, 100), args.seconds, _out)


_BY_NAME: dict[str, Callable[[argparse.Namespace], int]] = {"cli": _cli, "fleet": _fleet}
"""The benchmarks that take only their arguments (imported when run)."""


def _dry_run(args: argparse.Namespace) -> int:
    """``bench dry-run``: the ratio to real time (the median of ``--runs``), or with
    ``--bytecodes`` one scan's cost by function."""
    if args.bytecodes:
        from supervisor.bench.dryruncost import scan_cost

        cost = scan_cost(args.recipe)
        _out(
            f"dry run of {args.recipe}: {cost.bytecodes:,.0f} bytecodes and {cost.calls:.1f}"
            f" Python calls a scan (the difference of two traced runs, {cost.scans} scans)"
        )
        _out(f"{'bytecodes':>10} {'calls':>6}  function")
        for where, ops, calls in cost.by_function[:30]:
            _out(f"{ops:10.1f} {calls:6.2f}  {where}")
        return 0
    from supervisor.app.dryrun import dry_run, format_report

    # Several runs in one process, their median recorded: one run's ratio moves by a
    # fifth with what else the machine does (issue 13: 25 000–31 000× on the idle
    # machine), the median of five much less.
    ratios: list[float] = []
    walls: list[float] = []
    # The CPU-time ratio beside the wall one: on a shared machine (issue 29, load average
    # 3-12) the wall ratio moved threefold, the CPU-time ratio by about a tenth (ADR 0046).
    cpu_ratios: list[float] = []
    for k in range(args.runs):
        res = asyncio.run(dry_run(args.recipe, soc=0.0))
        ratios.append(res.ratio)
        walls.append(res.wall_s)
        cpu_ratios.append(res.cpu_ratio)
        _out(
            f"run {k + 1} of {args.runs}: {format_report(res)[-1]} (CPU time {res.cpu_ratio:,.0f}x)"
        )
    for line in format_report(res)[-3:-1]:
        _out(line)
    median = statistics.median(ratios)
    cpu_median = statistics.median(cpu_ratios)
    _out(
        f"median of {args.runs} runs: {median:,.0f}x"
        f" (min–max {min(ratios):,.0f}–{max(ratios):,.0f}x);"
        f" CPU-time ratio median {cpu_median:,.0f}x"
    )
    from supervisor.bench import report

    report.record(
        f"dry run of {args.recipe}",
        median,
        "× real time",
        ">= 30000",
        f"median of {args.runs} runs, min–max {min(ratios):,.0f}–{max(ratios):,.0f}×,"
        f" {res.simulated_s / 3600:.1f} simulated h in {statistics.median(walls):.2f} s"
        f" wall (median), CPU-time ratio median {cpu_median:,.0f}×",
        f"supervisor bench dry-run --recipe {args.recipe} --runs {args.runs}",
    )
    return 0
