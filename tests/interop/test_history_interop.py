"""Interoperability of HistoryRead: node-opcua-client (not asyncua) reads the raw history of
a historised tag from the bench's server, without and with SignAndEncrypt, and gets the
samples the embedded historian stored, oldest first, with their source times; in pages of
7 with continuation points, the same samples; a tag that is not historised answers
Bad_HistoryOperationUnsupported.

One server for the module (as tests/integration/test_opcua_history.py): a bench recording
its history (opcuarig ``history=True``, virtual clock) runs a discharge on ch0 for 6 s of
simulated time, its history flushed to the file; then node-opcua only reads.
``room.temp`` is an I/O map tag with ``history: {enabled: false}``. node-opcua comes from
``make node_modules`` (tests/interop/package-lock.json).
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from commandrig import DISCHARGE, recipe
from opcuarig import CLIENT_URI, PASSWORDS, Rig, client_certificate, node, opcua_rig, pem_of, trust

from supervisor.commands import Command, Verb
from supervisor.publish.historian import StoredSample

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
INTEROP = Path(__file__).resolve().parent
SCRIPT = INTEROP / "history.js"
TAG = "ch0.discharged_ah"  # moves every scan of a discharge
NOT_KEPT = "room.temp"
# OPC UA DateTime has 100 ns ticks, asyncua's datetime 1 µs: a source time read back by
# another client is the stored one to within a microsecond (and a float's rounding).
TIME_TOLERANCE_S = 2e-6


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    tmp = tmp_path_factory.mktemp("interop-history")
    async with opcua_rig(tmp, history=True, unhistorised=(NOT_KEPT,)) as r:
        started = r.bench.commands.execute(
            Command.channel("ch0", Verb.START, "test", recipe=recipe(tmp, DISCHARGE))
        )
        assert started.accepted, started.reason
        await r.scans(60)  # 6 s of discharge at 0.1 s per scan
        historian = r.bench.historian
        assert historian is not None and historian.writer.flush()
        yield r


def stored(rig: Rig) -> list[StoredSample]:
    assert rig.bench.historian is not None
    samples = rig.bench.historian.query.samples(TAG, 0.0, 1e12).samples
    assert len(samples) > 10, "the discharge stored a moving charge"
    return samples


async def read_history(rig: Rig, tmp: Path, secure: bool) -> dict[str, object]:
    samples = stored(rig)
    cert_der, key = await client_certificate(tmp, "node")
    trust(rig, cert_der)
    cert_pem = pem_of(cert_der, tmp / "node-cert.pem")
    cfg = {
        "endpoint": rig.server.endpoint,
        "namespace": rig.server.namespace,
        "tag": TAG,
        "notKept": NOT_KEPT,
        # [start, end] in ms, widened by 1 ms: a JS Date holds milliseconds.
        "start": int(samples[0].t * 1000) - 1,
        "end": int(samples[-1].t * 1000) + 1,
        "user": "bob",  # a viewer: reading history needs no more
        "password": PASSWORDS["bob"],
        "secure": secure,
        "applicationUri": CLIENT_URI,
        "cert": str(cert_pem),
        "key": str(key),
        "pki": str(tmp / "node-pki"),
    }
    proc = await asyncio.create_subprocess_exec(
        node(), str(SCRIPT), json.dumps(cfg), cwd=INTEROP, stdout=asyncio.subprocess.PIPE
    )
    out, _ = await asyncio.wait_for(proc.communicate(), 120)
    result: dict[str, object] = json.loads(out.decode().splitlines()[-1])
    assert proc.returncode == 0, result.get("error")
    return result


def as_stored(values: object) -> list[tuple[object, str]]:
    assert isinstance(values, list)
    return [(v["value"], v["status"]) for v in values]


def source_times(values: object) -> list[float]:
    assert isinstance(values, list)
    return [float(v["source"]) for v in values]


@pytest.mark.parametrize("secure", [False, True], ids=["None", "SignAndEncrypt"])
async def test_node_opcua_reads_the_raw_history_the_historian_stored(
    rig: Rig, tmp_path: Path, secure: bool
) -> None:
    samples = stored(rig)
    seen = await read_history(rig, tmp_path, secure)
    whole = seen["whole"]
    assert isinstance(whole, dict)
    assert (whole["status"], whole["more"]) == ("Good", False)
    assert as_stored(whole["values"]) == [(s.value, "Good") for s in samples]
    times = source_times(whole["values"])
    assert times == pytest.approx([s.t for s in samples], abs=TIME_TOLERANCE_S, rel=0)
    assert times == sorted(times)  # oldest first
    pages = seen["pages"]
    assert isinstance(pages, list)
    assert all(p["status"] == "Good" for p in pages)
    assert [len(p["values"]) for p in pages[:-1]] == [7] * (len(pages) - 1)
    assert 1 <= len(pages[-1]["values"]) <= 7
    assert [v for p in pages for v in as_stored(p["values"])] == as_stored(whole["values"])
    assert seen["notKept"] == {"status": "BadHistoryOperationUnsupported", "count": 0}
