"""Issue 28, finding 1: one encoding policy for every writer (``core/encoding.py``). Each
writer is handed a text holding a lone surrogate (what a JSON ``"\\ud800"`` gives), and
stores it escaped (``\\ud800``) instead of raising: the line protocol, the InfluxDB spool,
the retained state, the result files, the OPC UA feed, the event feed and the log lines.
(The historian's own test is in test_historian.py.)
"""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path

from supervisor.app.events import EventFeed
from supervisor.core.encoding import StorableFormatter, storable, storable_text, unencodable_at
from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.publish.changes import Sample
from supervisor.publish.influx.lineproto import LineEncoder
from supervisor.publish.influx.spool import Spool
from supervisor.publish.opcua.feed import AlarmView, OpcUaFeed
from supervisor.publish.provenance import write_once
from supervisor.publish.results import _append_line, _open_jsonl, read_jsonl
from supervisor.publish.retain import STATE_NAME, RetainStore
from supervisor.tags import TagDB, TagSpec

BAD = "x\ud800y\udcff"
ESCAPED = "x\\ud800y\\udcff"
WALL = 1_760_000_000.0


def utf8(text: str) -> bytes:
    return text.encode("utf-8")  # raises for what a writer could not store


def test_only_what_utf8_cannot_encode_is_escaped_and_a_good_text_is_kept_as_it_is() -> None:
    good = "Répos 25 °C \\ud800 ✓"
    assert storable_text(good) is good
    assert storable_text(BAD) == ESCAPED
    assert storable(3.5) == 3.5 and storable(BAD) == ESCAPED
    assert unencodable_at(BAD) == 1 and unencodable_at(good) is None


def test_the_line_protocol_escapes_a_surrogate_in_values_tags_and_events() -> None:
    encoder = LineEncoder("b1", ("ch0",), lambda name: "str" if "state" in name else None)
    lines = encoder.encode(
        [Sample("ch0.chain.state", BAD, Quality.GOOD, 0.0, WALL)], {"ch0": (BAD, "r", "c")}
    )
    event = encoder.event(BenchEvent(0.0, WALL, "command", "ch0", "s", BAD, "hmi:x"))
    for line in [*lines["channel"], event]:
        assert ESCAPED.encode() in utf8(line) or b"x\\\\ud800y" in utf8(line), line


def test_the_influx_spool_stores_the_encoded_lines(tmp_path: Path) -> None:
    encoder = LineEncoder("b1", ("ch0",), lambda name: "str")
    event = encoder.event(BenchEvent(0.0, WALL, "command", "ch0", "s", BAD, "hmi:x"))
    spool = Spool(tmp_path / "spool.sqlite", 1 << 30)
    spool.open()
    try:
        spool.append([("event", [event])], 100)
        assert spool.counts().waiting == 1
        batch = spool.next_batch(10)
        assert batch is not None and b"x\\\\ud800y" in b"".join(batch.lines())
    finally:
        spool.close()


def test_the_retained_state_keeps_a_surrogate_in_a_key_or_a_document(tmp_path: Path) -> None:
    store = RetainStore(tmp_path / STATE_NAME)
    store.open()
    store.put(f"channel:{BAD}", {"message": BAD})
    assert store.flush()
    assert store.read() == {f"channel:{ESCAPED}": {"message": BAD}}  # JSON's own \ud800
    store.close()


def test_result_files_write_a_surrogate_escaped(tmp_path: Path) -> None:
    path = tmp_path / "timeline.jsonl"
    f = _open_jsonl(path)
    try:
        _append_line(f, {"message": BAD})
        _append_line(f, {"message": "after"})
    finally:
        f.close()
    utf8(path.read_text(encoding="utf-8"))
    assert [line["message"] for line in read_jsonl(path)] == [BAD, "after"]
    assert write_once(tmp_path / "provenance.json", {"operator": BAD})
    assert json.loads((tmp_path / "provenance.json").read_text("utf-8")) == {"operator": BAD}


def test_the_opcua_feed_serves_a_surrogate_escaped() -> None:
    db = TagDB()
    tag = db.add(TagSpec("ch0.chain.message", dtype="str", initial=""))
    db.update(tag, BAD)
    feed = OpcUaFeed(db)
    (update,) = [u for u in feed.start(db, lambda: None) if u.name == "ch0.chain.message"]
    assert update.value == ESCAPED
    feed.on_alarm(AlarmView("a", "", 500, BAD, "active", True, False))
    feed.on_event(BenchEvent(0.0, WALL, "command", "ch0", "s", BAD, "hmi:x"))
    events = feed.take_events()
    assert [getattr(e, "message", None) or getattr(e, "text", None) for e in events] == [
        ESCAPED,
        ESCAPED,
    ]


def test_the_event_feed_hands_every_sink_a_storable_event() -> None:
    got: list[BenchEvent] = []

    class Sink:
        def on_event(self, event: BenchEvent) -> None:
            got.append(event)

    feed = EventFeed()
    feed.sinks.append(Sink())
    feed._emit(BenchEvent(0.0, WALL, "command", "ch0", BAD, f"mode {BAD}", BAD))
    (ev,) = got
    assert (ev.source, ev.text, ev.actor) == (ESCAPED, f"mode {ESCAPED}", ESCAPED)


def test_a_log_line_with_a_surrogate_is_written_escaped_on_a_strict_stream() -> None:
    raw = io.BytesIO()
    stream = io.TextIOWrapper(raw, encoding="utf-8", errors="strict", write_through=True)
    handler = logging.StreamHandler(stream)
    handler.setFormatter(StorableFormatter("%(message)s"))
    logger = logging.getLogger("test.storable")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        logger.warning("mode %s refused", BAD)
    finally:
        logger.removeHandler(handler)
    assert raw.getvalue() == f"mode {ESCAPED} refused\n".encode()
