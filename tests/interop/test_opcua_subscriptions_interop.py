"""Subscriptions as an integrator's node-opcua client (not asyncua) sees them: deadbands and
timestamps (issue 31, findings 2 and 6; OPC UA Part 4 §7.22.2, §7.10, §7.11, §7.40, Part 8
§6.2).

One server and one node-opcua client for the module. The bench (opcuarig, virtual clock)
has three probe tags of its own, driven by the test one sample a scan: a current ramp
(0 → 0.30 A in 0.05 A steps, EURange −0.4…0.4 A), a noisy current around 1 A (seeded,
EURange 0…2 A) and an integer counter (0, 1, 2, …, no EURange); a text tag for a deadband
that does not apply. The client monitors them with absolute and percent deadbands (queues
large enough to lose nothing, so what it receives is exactly what the server reported),
and each test compares what node-opcua received with the sequence Part 4 prescribes,
computed here from the samples the server was given: a sample is reported when it is more
than the deadband away from the **last value reported** (percent: that share of the
EURange the client read). Each signal ends with a sample far from everything before it:
once the client has it, it has everything before it (one item's notifications keep their
order), so no test waits on a time.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import random
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

from supervisor.app import Bench
from supervisor.core.quality import Quality
from supervisor.tags import TagSpec

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
INTEROP = Path(__file__).resolve().parent
SCRIPT = INTEROP / "subscriptions.js"

RAMP, NOISE, COUNT, TEXT = "probe.ramp_a", "probe.noise_a", "probe.count", "probe.label"
RAMP_RANGE, NOISE_RANGE = (-0.4, 0.4), (0.0, 2.0)
RAMP_SAMPLES = [round(0.05 * i, 2) for i in range(7)] + [-0.35]  # the last: far from all
_noise = random.Random(31)
NOISE_SAMPLES = [round(min(1.9, max(0.1, _noise.gauss(1.0, 0.06))), 4) for _ in range(60)]
NOISE_SAMPLES.append(1.95)
COUNT_SAMPLES = [*range(50), 200]  # 5 s of a counter at 10 counts a second, then far off
IDLE_SCANS = 30  # scans after the signals end: nothing changes on the probes meanwhile

ITEMS: list[dict[str, Any]] = [
    {"name": "ramp_abs", "tag": RAMP, "deadband": "absolute", "value": 0.08},
    {"name": "ramp_pct", "tag": RAMP, "deadband": "percent", "value": 15.0},
    {"name": "noise_abs", "tag": NOISE, "deadband": "absolute", "value": 0.05},
    {"name": "noise_pct", "tag": NOISE, "deadband": "percent", "value": 5.0},
    {"name": "count_abs", "tag": COUNT, "deadband": "absolute", "value": 5},
    {"name": "count_pct", "tag": COUNT, "deadband": "percent", "value": 10.0},
    {"name": "text_abs", "tag": TEXT, "deadband": "absolute", "value": 1.0},
    {"name": "count_source", "tag": COUNT, "deadband": None, "timestamps": "Source"},
    {"name": "count_neither", "tag": COUNT, "deadband": None, "timestamps": "Neither"},
    {"name": "count_status", "tag": COUNT, "deadband": None, "trigger": "Status"},
]
LAST = {"ramp_abs": -0.35, "ramp_pct": -0.35, "noise_abs": 1.95, "noise_pct": 1.95}
LAST |= {"count_abs": 200, "count_source": 200, "count_neither": 200}


def part4(samples: list[float], deadband: float) -> list[float]:
    """Part 4 §7.22.2: the samples a monitored item with this absolute deadband reports."""
    out: list[float] = []
    for x in samples:
        if not out or abs(x - out[-1]) > deadband:
            out.append(x)
    return out


def written(samples: list[Any]) -> list[Any]:
    """What the server is given of a signal: each change (a repeat changes no tag)."""
    return [x for i, x in enumerate(samples) if i == 0 or x != samples[i - 1]]


@dataclass
class Seen:
    """What the node-opcua client saw, and the server's log meanwhile."""

    ready: dict[str, Any]
    received: dict[str, list[dict[str, Any]]]
    read: dict[str, dict[str, Any]]
    heard_ms: float  # the last scan's time before the read, ms since 1970
    sampling_ms: float  # the server's sampling interval (a hand-over at most this often)
    changed_ms: float  # when the counter last changed
    log: list[str] = field(default_factory=list)


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def probes(bench: Bench) -> None:
    db = bench.db
    for spec in (
        TagSpec(RAMP, unit="A", range=RAMP_RANGE, description="interop probe: a ramp"),
        TagSpec(NOISE, unit="A", range=NOISE_RANGE, description="interop probe: noise"),
        TagSpec(COUNT, dtype="int", description="interop probe: a counter"),
        TagSpec(TEXT, dtype="str", description="interop probe: a text"),
    ):
        db.add(spec)
    db.update(db[RAMP], RAMP_SAMPLES[0])
    db.update(db[NOISE], NOISE_SAMPLES[0])
    db.update(db[COUNT], COUNT_SAMPLES[0])
    db.update(db[TEXT], "probe")


async def said(proc: asyncio.subprocess.Process) -> dict[str, Any]:
    """The script's next line of its own (node-opcua writes warnings too)."""
    assert proc.stdout is not None
    while True:
        raw = await asyncio.wait_for(proc.stdout.readline(), 120)
        if not raw:
            raise AssertionError("subscriptions.js ended without answering")
        line = raw.decode()
        if line.startswith("@@ "):
            message: dict[str, Any] = json.loads(line[3:])
            assert "error" not in message, message["error"]
            return message


async def ask(proc: asyncio.subprocess.Process, command: dict[str, Any]) -> dict[str, Any]:
    assert proc.stdin is not None
    proc.stdin.write((json.dumps(command) + "\n").encode())
    await proc.stdin.drain()
    return await said(proc)


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def seen(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Seen]:
    tmp = tmp_path_factory.mktemp("interop-subscriptions")
    lines = Lines()
    asyncua_log = logging.getLogger("asyncua")
    asyncua_log.addHandler(lines)
    try:
        async with opcua_rig(tmp, prepare=probes) as rig:
            got = await drive(rig, tmp)
            got.log = lines.lines  # kept filling until the module's tests are done
            yield got
    finally:
        asyncua_log.removeHandler(lines)


async def drive(rig: Rig, tmp: Path) -> Seen:
    cert_der, key = await client_certificate(tmp, "node")
    trust(rig, cert_der)  # finding 1 (the None endpoint and certificates) is not this file's
    cert_pem = pem_of(cert_der, tmp / "node-cert.pem")
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "items": ITEMS,
        "ranges": [RAMP, NOISE, COUNT],
        "user": "bob",  # a viewer: subscribing needs no more
        "password": PASSWORDS["bob"],
        "applicationUri": CLIENT_URI,
        "cert": str(cert_pem),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
    }
    proc = await asyncio.create_subprocess_exec(
        node(),
        str(SCRIPT),
        json.dumps(cfg),
        cwd=INTEROP,
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        ready = await said(proc)
        db, settings = rig.bench.db, rig.settings
        per_sample = max(1, math.ceil(settings.sampling_interval_s / settings.scan_period_s - 1e-9))
        for i in range(max(len(RAMP_SAMPLES), len(NOISE_SAMPLES), len(COUNT_SAMPLES))):
            for tag, samples in (
                (RAMP, RAMP_SAMPLES),
                (NOISE, NOISE_SAMPLES),
                (COUNT, COUNT_SAMPLES),
            ):
                if i < len(samples):
                    db.update(db[tag], samples[i], Quality.GOOD)
            await rig.scans(per_sample)  # handed over and written before the next sample
        received = (await ask(proc, {"until": LAST}))["received"]
        changed_t = db[COUNT].server_t
        await rig.scans(IDLE_SCANS)
        clock = rig.bench.clock
        heard_t = max(t.server_t for t in db)
        read = (await ask(proc, {"read": COUNT}))["read"]
        await ask_end(proc)
        return Seen(
            ready,
            received,
            read,
            heard_ms=clock.to_wall(heard_t) * 1000.0,
            sampling_ms=settings.sampling_interval_s * 1000.0,
            changed_ms=clock.to_wall(changed_t) * 1000.0,
        )
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def ask_end(proc: asyncio.subprocess.Process) -> None:
    assert proc.stdin is not None
    proc.stdin.write(b'{"end": true}\n')
    await proc.stdin.drain()
    await asyncio.wait_for(proc.wait(), 60)
    assert proc.returncode == 0


def values(seen: Seen, item: str) -> list[Any]:
    return [n["value"] for n in seen.received[item]]


def band_of(seen: Seen, tag: str, percent: float) -> float:
    rng = seen.ready["ranges"][tag]
    assert rng is not None, f"{tag} has no EURange"
    return percent / 100.0 * (rng["high"] - rng["low"])


# --- finding 2: deadbands ----------------------------------------------------------------------
async def test_every_item_is_created_but_those_a_deadband_does_not_apply_to(seen: Seen) -> None:
    assert seen.ready["created"] == {
        "ramp_abs": "Good",
        "ramp_pct": "Good",
        "noise_abs": "Good",
        "noise_pct": "Good",
        "count_abs": "Good",
        # An Int64 counter is no AnalogItem (no EURange): the filter is valid, this item
        # cannot support it (Part 4 Table 183, as node-opcua's own server answers).
        "count_pct": "BadMonitoredItemFilterUnsupported",
        # A deadband is for Number variables only (Part 4 §7.22.2).
        "text_abs": "BadFilterNotAllowed",
        "count_source": "Good",
        "count_neither": "Good",
        "count_status": "Good",
    }


async def test_an_absolute_deadband_compares_with_the_last_value_reported(seen: Seen) -> None:
    # The ramp's steps (0.05 A) are all under the deadband (0.08 A): compared with the
    # previous sample it never reaches the client; compared with the last report it does.
    assert (
        values(seen, "ramp_abs")
        == part4(written(RAMP_SAMPLES), 0.08)
        == [0.0, 0.1, 0.2, 0.3, -0.35]
    )
    assert values(seen, "noise_abs") == part4(written(NOISE_SAMPLES), 0.05)
    assert 3 < len(values(seen, "noise_abs")) < len(written(NOISE_SAMPLES))


async def test_a_counter_under_a_deadband_of_five_is_reported_about_nine_times_in_five_s(
    seen: Seen,
) -> None:
    got = values(seen, "count_abs")
    assert got == part4(COUNT_SAMPLES, 5) == [0, 6, 12, 18, 24, 30, 36, 42, 48, 200]


async def test_a_percent_deadband_is_that_share_of_the_eu_range_the_client_reads(
    seen: Seen,
) -> None:
    assert seen.ready["ranges"][RAMP] == {"low": RAMP_RANGE[0], "high": RAMP_RANGE[1]}
    ramp_band = band_of(seen, RAMP, 15.0)  # 0.12 A
    noise_band = band_of(seen, NOISE, 5.0)  # 0.1 A
    assert values(seen, "ramp_pct") == part4(written(RAMP_SAMPLES), ramp_band)
    assert values(seen, "ramp_pct") == [0.0, 0.15, 0.3, -0.35]
    assert values(seen, "noise_pct") == part4(written(NOISE_SAMPLES), noise_band)
    assert len(values(seen, "noise_pct")) < len(values(seen, "noise_abs"))


async def test_no_deadband_reports_every_change(seen: Seen) -> None:
    assert values(seen, "count_source") == COUNT_SAMPLES


async def test_the_trigger_status_reports_status_changes_only(seen: Seen) -> None:
    # The counter stayed Good: its first value only (the others' last values have come,
    # and they were queued after every sample of this item).
    assert values(seen, "count_status") == [COUNT_SAMPLES[0]]


# --- finding 6: timestamps -----------------------------------------------------------------------
async def test_a_read_returns_the_timestamps_asked_for(seen: Seen) -> None:
    present = {
        ttr: (got["source"] is not None, got["server"] is not None)
        for ttr, got in seen.read.items()
    }
    assert present == {
        "Source": (True, False),
        "Server": (False, True),
        "Both": (True, True),
        "Neither": (False, False),
    }


async def test_a_monitored_item_sends_the_timestamps_it_asked_for(seen: Seen) -> None:
    def present(item: str) -> set[tuple[bool, bool]]:
        return {(n["source"] is not None, n["server"] is not None) for n in seen.received[item]}

    assert present("count_abs") == {(True, True)}
    assert present("count_source") == {(True, False)}
    assert present("count_neither") == {(False, False)}


async def test_the_server_timestamp_of_an_unchanged_value_is_when_it_was_last_known_current(
    seen: Seen,
) -> None:
    both = seen.read["Both"]
    assert both["value"] == COUNT_SAMPLES[-1]
    # The value changed IDLE_SCANS scans ago: its source time says when; the server knew it
    # current at the scan's last hand-over, 3 s later: the last scan's time, or the one
    # before when the last scan changed nothing before its hand-over (the scan's own counters
    # are set after its publishers ran). A JS Date holds milliseconds.
    assert both["source"] == pytest.approx(seen.changed_ms, abs=1.0)
    assert seen.heard_ms - seen.sampling_ms - 1.0 <= both["server"] <= seen.heard_ms + 1.0
    assert both["server"] - both["source"] > 2000.0


async def test_no_deadband_warning_is_logged(seen: Seen) -> None:
    assert seen.received  # the exchange ran
    assert not [line for line in seen.log if "Percent is not implemented" in line]
