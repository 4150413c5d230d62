"""Must show 3 of issue 36: a SCADA client polling 1000 registers every 10 ms costs the scan
nothing — shown by the scan's own counters (overruns, missed deadlines: 0), never by a
timing claim. The poller runs in a process of its own (tests/modbus_rig.py): in this one it
would be part of what is measured. The server answers from its register image on its own
thread, between scans (ADR 0032).

Wall clock: io_maps/sim.yaml on free loopback ports, scanning every 10 ms.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import pytest
import yaml

from supervisor.app.service import serve
from supervisor.bench.subject import prepare
from supervisor.devices.registry import load_bench
from supervisor.publish.modbus.regmap import RegisterMap, Table

# It asserts the scan kept its timing (no overrun) under load it makes itself: it runs
# alone, after the tests that run in parallel (Makefile: the "quiet" marker).
pytestmark = [pytest.mark.integration, pytest.mark.quiet]

ROOT = Path(__file__).resolve().parents[2]
REGISTERS = 1000
PERIOD_S = 0.01
SECONDS = 5.0
MAX_READ = 125  # registers one FC 04 may ask for


def reads_of(regmap: RegisterMap, registers: int) -> list[tuple[int, int]]:
    """(address, count) reads of served input registers, ``registers`` in all: the map's
    contiguous runs cut at 125, again from the start until there are enough."""
    served = sorted(
        a
        for p in regmap.in_table(Table.INPUT_REGISTER)
        for a in range(p.address, p.address + p.words)
    )
    runs: list[tuple[int, int]] = []
    for a in served:
        if runs and runs[-1][0] + runs[-1][1] == a and runs[-1][1] < MAX_READ:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((a, 1))
    out: list[tuple[int, int]] = []
    total = 0
    while total < registers:
        for address, count in runs:
            count = min(count, registers - total)
            out.append((address, count))
            total += count
            if total == registers:
                break
    return out


async def test_a_client_polling_1000_registers_every_10_ms_costs_the_scan_no_overrun(
    tmp_path: Path,
) -> None:
    copy, _, _ = prepare(ROOT / "io_maps" / "sim.yaml", tmp_path)
    data = yaml.safe_load(copy.read_text(encoding="utf-8"))
    data["hmi"]["login"] = False
    data["scan"]["period_s"] = PERIOD_S
    copy.write_text(yaml.safe_dump(data, allow_unicode=True, sort_keys=False), encoding="utf-8")
    async with serve(load_bench(copy)) as sup:
        server = sup.modbus
        assert server is not None
        reads = reads_of(server.regmap, REGISTERS)
        spec = ",".join(f"{a}:{n}" for a, n in reads)
        stats = sup.bench.engine.stats
        start = stats.count
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            str(ROOT / "tests" / "modbus_rig.py"),
            server.host,
            str(server.bound_port),
            str(SECONDS),
            str(PERIOD_S),
            spec,
            stdout=asyncio.subprocess.PIPE,
        )
        try:
            out, _ = await asyncio.wait_for(proc.communicate(), SECONDS + 60)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        result = json.loads(out.decode().splitlines()[-1])
        scans = stats.count - start
        longest_ms = 1000 * float(sup.bench.db["scan.duration_max_s"].value or 0.0)
        assert (stats.overruns, stats.skipped) == (0, 0)  # the scan kept its period
    print(
        f"modbus load: {result['polls']} polls, {result['registers']} registers, {scans} scans,"
        f" longest scan {longest_ms:.2f} ms, overruns {stats.overruns}"
    )
    assert result["errors"] == []
    assert result["registers"] == result["polls"] * REGISTERS
    assert result["polls"] > 0 and scans > 0
