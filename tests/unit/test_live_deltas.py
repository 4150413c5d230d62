"""The WebSocket hub's deltas and snapshots from the kept texts (``supervisor.hmi.live``,
docs/adr/0019-http-off-the-scan.md "Kept texts"): each delta is exactly the JSON text of
the tags newer than what its client has, for a client at the last publication as for one
that joined since or must catch up; a page's snapshot after a delta encodes again only
what changed since."""

from __future__ import annotations

import asyncio
import json
from typing import Any

from supervisor.core.clock import VirtualClock
from supervisor.core.records import BenchEvent
from supervisor.hmi.live import LiveClient, LiveHub, tag_entry
from supervisor.hmi.server import json_dumps
from supervisor.tags import TagDB, TagSpec


def _db(n: int) -> TagDB:
    db = TagDB()
    for k in range(n):
        db.update(db.add(TagSpec(f"t{k:03d}", unit="V")), k * 0.25)
    db.update(db.add(TagSpec("text", dtype="str")), 'a "quoted" ü')
    return db


def _client(version: int) -> LiveClient:
    # The hub only queues texts for it here: no socket is written.
    return LiveClient(ws=None, version=version, queue_size=16, valid=lambda: True)  # type: ignore[arg-type]


def _delta_text(db: TagDB, clock: VirtualClock, since: int) -> str:
    tags = db.changed_since(since)
    body: dict[str, Any] = {"type": "delta", "version": db.version}
    body["tags"] = {t.name: tag_entry(t, clock) for t in tags}
    return json_dumps(body)


def test_each_client_gets_the_text_of_the_tags_newer_than_its_version(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(40)
    hub = LiveHub(db, virtual_clock, publish_period_s=0.2)
    tags = list(db)

    async def scenario() -> None:
        await hub.publish()  # the hub's version is the database's now
        base = hub.version
        for t in tags[:10]:
            db.update(t, -1.0)
        joined = db.version  # a page whose snapshot was at this version
        for t in tags[5:15]:
            db.update(t, -2.0)
        db.update(db["text"], 'ünï "côdé" \\ \n')
        at_base, newcomer, behind = _client(base), _client(joined), _client(base - 3)
        hub.clients.update((at_base, newcomer, behind))
        expected = {
            id(c): _delta_text(db, virtual_clock, since)
            for c, since in ((at_base, base), (newcomer, joined), (behind, base - 3))
        }
        await hub.publish()
        for c in (at_base, newcomer, behind):
            text = c.queue.get_nowait()
            assert text == expected[id(c)]
            assert c.version == db.version
        assert json.loads(expected[id(newcomer)])["tags"].keys() == {
            *(t.name for t in tags[5:15]),
            "text",
        }

    asyncio.run(scenario())


def test_a_snapshot_after_a_delta_encodes_again_only_what_changed_since(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(40)
    hub = LiveHub(db, virtual_clock, publish_period_s=0.2)
    fragments = hub.snapshots.fragments[True]

    async def scenario() -> None:
        await hub.snapshots.image(as_map=True)
        hub.clients.add(_client(db.version))
        encoded = fragments.encoded
        for t in list(db)[:8]:
            db.update(t, 99.0)
        await hub.publish()  # the delta encodes the 8 changed tags and keeps their texts
        assert fragments.encoded == encoded + 8
        db.update(db["t020"], 5.5)
        version, text = await hub.snapshots.image(as_map=True)
        assert fragments.encoded == encoded + 9
        by_name = {t.name: tag_entry(t, virtual_clock) for t in db}
        assert (version, text) == (db.version, json_dumps(by_name))

    asyncio.run(scenario())


def test_a_bench_event_reaches_the_pages_with_the_next_publication_before_its_delta(
    virtual_clock: VirtualClock,
) -> None:
    """An event from the scan (a step change) is kept, not encoded there: the next
    publication sends it to every page, then the delta with the tags that changed."""
    db = _db(3)
    hub = LiveHub(db, virtual_clock, publish_period_s=0.2)

    async def scenario() -> None:
        await hub.publish()
        page = _client(hub.version)
        hub.clients.add(page)
        db.update(db["t000"], 9.0)
        hub.on_event(BenchEvent(5.0, 1_767_225_605.0, "step", "ch0", "charge", "starting step 1"))
        assert page.queue.empty()  # nothing made or queued in the scan
        await hub.publish()
        event, delta = json.loads(page.queue.get_nowait()), json.loads(page.queue.get_nowait())
        assert event == {
            "type": "event",
            "event": {
                "wall": 1_767_225_605.0,
                "kind": "step",
                "channel": "ch0",
                "source": "charge",
                "text": "starting step 1",
                "actor": "",
                "severity": 0,
                "test_id": "",
                "recipe": "",
            },
        }
        assert delta["type"] == "delta" and list(delta["tags"]) == ["t000"]

    asyncio.run(scenario())
