"""``supervisor bench load|memory|pi-budget|report``: the whole-supervisor benchmarks, the
table."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from supervisor.bench import report
from supervisor.core.errors import ConfigError


def run(args: argparse.Namespace) -> int:
    if args.what == "load":
        from supervisor.bench.load import load_benchmark

        warm = 10.0 if args.warmup is None else args.warmup
        return load_benchmark(
            args.seconds,
            warm,
            args.http_rate,
            clients_nice=args.clients_nice,
            sim_in_process=args.sim_in_process,
        )
    if args.what == "memory":
        from supervisor.bench.memory import memory_benchmark

        trace = Path(args.trace) if args.trace else None
        if args.virtual:
            from supervisor.bench.memory import virtual_trace

            if trace is None:
                raise ConfigError("bench memory --virtual: give --trace DIR (the snapshots)")
            return virtual_trace(args.minutes, args.warmup, trace)
        return memory_benchmark(args.minutes, args.warmup, trace_dir=trace)
    if args.what == "pi-budget":
        from supervisor.bench.pibudget import WARMUP_S, pi_budget_benchmark

        return pi_budget_benchmark(args.seconds, WARMUP_S if args.warmup is None else args.warmup)
    lines = Path(os.environ.get(report.ENV) or Path(args.out) / "results.jsonl")
    js, md = report.write_report(lines, Path(args.out))
    sys.stdout.write(md.read_text(encoding="utf-8"))
    sys.stdout.write(f"written: {js}, {md}\n")
    return 0
