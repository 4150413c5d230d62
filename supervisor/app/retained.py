"""Retained state wiring: what each channel saves, when, and how a restart brings it back.

docs/design.md "Safety": per channel the state that matters — test id, recipe (its text, file
name and parameters, so it recompiles the same even if the file changed or moved), chain
state and step, step time, cycle, the run's time and counter baselines, the Ah/Wh counters
(the ``retain=True`` tags), the mode — and the bench's latched alarms are persisted; after
a restart a channel whose test was under way comes back Held at the same step with
``resume`` available, never re-energised on its own (seed 001 saves its context before
every alarm so that an interrupted test resumes later).

When: at the end of every scan in which a channel's chain changed step or state, wrote a
result record, or an alarm changed (chain events, records, alarm events), and every
``retain.period_s``. The scan only builds
plain documents (``Retention.on_scan`` is a scan publisher); ``RetainStore``'s worker
thread writes them. A write failure raises the ``retain.write`` alarm until a write
succeeds again; an unreadable state file, or a test that cannot be brought back (its
recipe no longer compiles against the channel), raises ``retain.restore`` and the channel
starts Idle — its result folder and summary say why.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from supervisor.chains.compiler import compile_recipe
from supervisor.chains.run import ChainSnapshot
from supervisor.chains.states import ACTIVE, State
from supervisor.config.recipe import load_recipe_text
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.core.records import ChainEvent, Record
from supervisor.publish.results import TIMELINE_KINDS, ResultCollector
from supervisor.publish.retain import STATE_NAME, Document, RetainStore
from supervisor.safety import AlarmEvent, Severity
from supervisor.tags import TagDB, TagSpec
from supervisor.tags.spec import shown

if TYPE_CHECKING:
    from supervisor.app.bench import Bench

log = logging.getLogger(__name__)

WRITE_ALARM = "retain.write"
RESTORE_ALARM = "retain.restore"
ACTIVE_VALUES = frozenset(s.value for s in ACTIVE)
_EPS_S = 1e-9


@dataclass(frozen=True)
class RecipeSource:
    """A recipe as it was compiled for a test: a restart recompiles this text, not the
    file (which may have changed or moved since)."""

    file: str
    text: str
    parameters: dict[str, str] = field(default_factory=dict)
    folder: str = ""  # the test's result folder

    def as_dict(self) -> dict[str, Any]:
        """``dataclasses.asdict(self)`` without its recursion: a channel's document is
        built at each of its result records (every second of a test, 16 channels in the
        same scan in issue 13's load case)."""
        return {
            "file": self.file,
            "text": self.text,
            "parameters": dict(self.parameters),
            "folder": self.folder,
        }

    @classmethod
    def from_dict(cls, data: Any) -> RecipeSource:
        """The source of ``as_dict``; ValueError naming the field and what it holds when
        it is not what ``as_dict`` writes (texts, parameters as texts)."""
        if not isinstance(data, dict):
            raise ValueError(f"recipe: {shown(data)} is not a mapping")
        unknown = sorted(set(data) - {"file", "text", "parameters", "folder"})
        if unknown:
            raise ValueError(f"recipe: unknown field {', '.join(map(repr, unknown))}")
        if not isinstance(data.get("text"), str):
            raise ValueError(f"recipe field text: {shown(data.get('text'))} is not a text")
        for key in ("file", "folder"):
            if not isinstance(data.get(key, ""), str):
                raise ValueError(f"recipe field {key}: {shown(data.get(key))} is not a text")
        params = data.get("parameters", {})
        if not isinstance(params, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in params.items()
        ):
            raise ValueError(
                f"recipe field parameters: {shown(params)} is not a mapping of texts to texts"
                if not isinstance(params, dict)
                else "recipe field parameters: a name or value is not a text"
            )
        return cls(data.get("file", ""), data["text"], dict(params), data.get("folder", ""))


def recipe_program(bench: Bench, channel: str, src: RecipeSource) -> Any:
    """Compile ``src`` for ``channel`` (ConfigErrors with file:line:col when it does not)."""
    recipe, pos = load_recipe_text(src.text, src.file)
    return compile_recipe(recipe, pos, src.file, bench.target(channel), src.parameters)


def _errors_text(exc: ConfigError | ConfigErrors) -> str:
    if isinstance(exc, ConfigErrors):
        return "; ".join(e.location_message() for e in exc.errors)
    return exc.location_message()


class Retention:
    """Saves the bench's retained state off the scan (a scan publisher) and restores it."""

    name = "retain"

    def __init__(
        self,
        bench: Bench,
        store: RetainStore,
        period_s: float = 1.0,
        summary_period_s: float = 10.0,
    ) -> None:
        assert bench.alarms is not None
        self.bench = bench
        self.store = store
        self.period_s = period_s
        self.summary_period_s = summary_period_s
        alarms = bench.alarms
        self.write_alarm = alarms.declare(WRITE_ALARM, severity=Severity.HIGH)
        self.restore_alarm = alarms.declare(RESTORE_ALARM, severity=Severity.HIGH)
        db = bench.db
        self._error_tag = db.add(
            TagSpec(
                "retain.error",
                dtype="str",
                initial="",
                description="Why the retained state is not being saved ('' when it is)",
            )
        )
        self._restore_tag = db.add(
            TagSpec(
                "retain.restore",
                dtype="str",
                initial="",
                description="What the last start-up could not bring back ('' when all)",
            )
        )
        db.update(self._error_tag, "")
        db.update(self._restore_tag, "")
        self.report: list[str] = []  # what the restore did, one line each
        self._aside: str | None = None  # where a copy of a refused state file went
        self._dirty: set[str] = set(bench.runners)
        self._alarms_dirty = True
        self._last_save_t = -math.inf
        # A periodic save is put one scan before its period is over: the worker commits it
        # after that scan (milliseconds), so a SIGKILL finds counters on disk at most one
        # ``period_s`` old (docs/operator.md "Retained state"), not a period plus the write.
        self._write_margin_s = bench.cfg.scan.period_s
        # Per channel: when its next periodic save and test summary are due (``_stagger``).
        self._save_due: dict[str, float] = {}
        self._summary_due: dict[str, float] = {}
        self._channel_tags = {
            ch: [t for t in db if t.spec.retain and t.name.startswith(f"{ch}.")]
            for ch in bench.channels
        }
        owned = {t.name for tags in self._channel_tags.values() for t in tags}
        self._bench_tags = [t for t in db if t.spec.retain and t.name not in owned]
        for name, runner in bench.runners.items():
            runner.listeners.append(self._chain_listener(name))
            # Saved with every result record too, so that the counters a restart brings
            # back are those of the last BDF row (not older: the file would go backwards).
            runner.recorders.append(self._record_listener(name))
        alarms.listeners.append(self._on_alarm)

    @classmethod
    def attach(cls, bench: Bench) -> Retention:
        """Open ``<state_dir>/state.sqlite``, restore what it holds, and save from now on."""
        cfg = bench.cfg
        store = RetainStore(Path(cfg.state_dir) / STATE_NAME, wall=bench.clock.wall)
        store.gate = bench.gate
        retention = cls(bench, store, cfg.retain.period_s, cfg.retain.summary_period_s)
        retention.restore()
        bench.engine.publishers.append(retention)
        return retention

    # --- when to save ------------------------------------------------------------------
    def _chain_listener(self, channel: str) -> Callable[[ChainEvent], None]:
        def on_event(ev: ChainEvent) -> None:
            if ev.kind in ("step", "state", "alarm"):
                self._dirty.add(channel)

        return on_event

    def _record_listener(self, channel: str) -> Callable[[Record], None]:
        def on_record(rec: Record) -> None:
            self._dirty.add(channel)

        return on_record

    def _on_alarm(self, ev: AlarmEvent) -> None:
        self._alarms_dirty = True

    def on_scan(self, db: TagDB, t: float) -> None:
        """At scan end: this scan's changes, and each channel at least every ``period_s``.

        The periodic saves and test summaries of the channels are spread over their period
        (channel *i* of *n* at *i/n* of it), not made in one scan: 16 channel documents and
        16 summaries in the same scan cost it 1–1.5 ms of a 10 ms period (issue 13's load
        case), and nothing is gained by saving them at the same instant."""
        self._report_write_error()
        store = self.store
        save_due, summary_due = self._save_due, self._summary_due
        if len(save_due) != len(self.bench.runners):
            self._stagger(t)
        channels = self._dirty
        every_s = self._save_every_s()
        for ch, due_t in save_due.items():
            if t >= due_t - _EPS_S:  # the scan due, not the next one by float noise
                channels.add(ch)
                # Its own grid, which a save on a change does not move (or they would all
                # line up again after a change saved every channel at once).
                nxt = due_t + every_s
                save_due[ch] = nxt if nxt > t else t + every_s
        for ch in sorted(channels):
            store.put(f"channel:{ch}", self.channel_document(ch))
        periodic = t - self._last_save_t >= self.period_s
        if periodic or self._alarms_dirty:
            store.put("alarms", self.alarms_document(t))
        if periodic:
            self._last_save_t = t
            if self._bench_tags:
                store.put("tags", {"tags": {tag.name: tag.value for tag in self._bench_tags}})
        self._dirty = set()
        self._alarms_dirty = False
        results = self.bench.results
        for ch, due_t in summary_due.items():
            if t < due_t:
                continue
            nxt = due_t + self.summary_period_s
            summary_due[ch] = nxt if nxt > t else t + self.summary_period_s
            collector = results.get(ch)
            runner = self.bench.runners[ch]
            if collector is not None and runner.state in ACTIVE and not collector.closed:
                collector.checkpoint(runner.state.value, now=t)

    def _save_every_s(self) -> float:
        """The periodic saves' interval: ``period_s`` less one scan (the write's time, see
        ``_write_margin_s``), never below half of ``period_s``."""
        period = self.period_s
        return max(period - self._write_margin_s, period / 2)

    def _stagger(self, t: float) -> None:
        """Each channel's next periodic save and summary, spread over their periods."""
        channels = sorted(self.bench.runners)
        n = len(channels)
        for i, ch in enumerate(channels):
            if ch not in self._save_due:
                self._save_due[ch] = t + self.period_s * i / n
                self._summary_due[ch] = t + self.summary_period_s * i / n

    def _report_write_error(self) -> None:
        err = self.store.error
        assert self.bench.alarms is not None
        text = f"retained state not saved ({self.store.path}): {err}" if err else ""
        self.bench.alarms.set(self.write_alarm, err is not None, text)
        if self._error_tag.value != text:
            self.bench.db.update(self._error_tag, text)

    # --- what is saved -----------------------------------------------------------------
    def channel_document(self, channel: str) -> Document:
        bench = self.bench
        runner = bench.runners[channel]
        snap = runner.snapshot()
        src = bench.recipes.get(channel)
        return {
            "channel": channel,
            "chain": snap.as_dict() if snap is not None else None,
            "recipe": src.as_dict() if src is not None and snap is not None else None,
            "tags": {tag.name: tag.value for tag in self._channel_tags.get(channel, [])},
            "mode": bench.db[f"{channel}.mode"].value,
        }

    def alarms_document(self, now: float) -> Document:
        """The alarms not back to normal (latched trips, unacknowledged ones)."""
        assert self.bench.alarms is not None
        out = []
        for a in self.bench.alarms:
            if a.id in (WRITE_ALARM, RESTORE_ALARM) or not (a.in_alarm or a.tripped):
                continue
            out.append(
                {
                    "id": a.id,
                    "message": a.message,
                    "active": a.active,
                    "acked": a.acked,
                    "tripped": a.tripped,
                    "first_out": a.first_out,
                    "acked_by": a.acked_by,
                    "since_s": None if a.activated_t is None else now - a.activated_t,
                }
            )
        return {"alarms": out}

    # --- after a restart -----------------------------------------------------------------
    def restore(self) -> list[str]:
        """Bring back what the store holds (before the first scan). Never raises for what
        is in the file: a problem is logged, raised as ``retain.restore`` and the channel
        concerned starts Idle."""
        loaded = self.store.open()
        if loaded.problem:
            self._problem(
                f"retained state {self.store.path} unreadable ({loaded.problem}); moved to"
                f" {loaded.moved_to}; every channel starts Idle"
            )
            return self.report
        docs = loaded.documents
        try:
            self._restore_alarms(docs.get("alarms"))
            self._restore_tags(self._tag_values("tags", (docs.get("tags") or {}).get("tags")))
        except (ValueError, TypeError, AttributeError, KeyError) as exc:
            self._problem(
                f"retained alarms or tags unreadable ({exc}); not restored; {self._copy_aside()}"
            )
        for key, doc in sorted(docs.items()):
            if not key.startswith("channel:"):
                continue
            channel = key.removeprefix("channel:")
            if channel not in self.bench.runners:
                self._problem(f"retained state of {channel}: no such channel in this bench")
                continue
            try:
                self._restore_channel(channel, doc)
            except (ValueError, TypeError, AttributeError, KeyError) as exc:
                self._problem(
                    f"{channel}: retained state unreadable ({exc}); starts Idle, its test"
                    f" not resumed; {self._copy_aside()}"
                )
        return self.report

    def _copy_aside(self) -> str:
        """A copy of the state file as it was read, beside it, once per start-up (the
        refused document is overwritten by the next save): where it is, as a sentence."""
        if self._aside is None:
            try:
                self._aside = f"the state file as it was is kept as {self.store.copy_aside()}"
            except OSError as exc:
                self._aside = f"no copy of the state file kept ({exc})"
        return self._aside

    def _problem(self, text: str) -> None:
        log.error("%s", text)
        self.report.append(text)
        assert self.bench.alarms is not None
        # Annunciated until acknowledged (returned, unacknowledged): it is a report, not a
        # condition that stays.
        self.bench.alarms.set(self.restore_alarm, True, text)
        self.bench.alarms.set(self.restore_alarm, False)
        shown = str(self._restore_tag.value or "")
        self.bench.db.update(self._restore_tag, f"{shown}; {text}" if shown else text)

    def _tag_values(self, where: str, values: Any) -> dict[str, Any]:
        """The retained tags' values of a document, each checked against its tag's type
        (a counter is a finite number): ValueError naming the tag and what it holds. A tag
        this bench does not retain (any more) is left out, said in the log."""
        if values is None:
            return {}
        if not isinstance(values, dict):
            raise ValueError(f"{where}: {shown(values)} is not a mapping of tags")
        db = self.bench.db
        out: dict[str, Any] = {}
        for name, value in values.items():
            tag = db.get(name)
            if tag is None or not tag.spec.retain:
                log.warning("retained tag %s: not retained on this bench; dropped", name)
                continue
            try:
                out[name] = None if value is None else tag.spec.coerce(value)
            except (TypeError, ValueError):
                raise ValueError(
                    f"{where}.{name}: {shown(value)} is not a {tag.spec.dtype} value"
                ) from None
        return out

    def _restore_tags(self, values: dict[str, Any]) -> None:
        db = self.bench.db
        for name, value in values.items():
            tag = db.get(name)
            if tag is not None and tag.spec.retain:
                db.update(tag, value)

    def _restore_alarms(self, doc: Document | None) -> None:
        if not doc:
            return
        alarms = self.bench.alarms
        assert alarms is not None
        now = self.bench.clock.now()
        records = doc.get("alarms")
        if not isinstance(records, list):
            raise ValueError(f"alarms: {shown(records)} is not a list")
        for rec in records:
            _check_alarm(rec)
        for rec in records:
            alarm_id = str(rec["id"])
            if alarm_id not in alarms:
                log.warning("retained alarm %s: not declared on this bench; dropped", alarm_id)
                continue
            a = alarms[alarm_id]
            # The condition itself is re-evaluated by its owner from the first scan: if
            # it is still present the alarm activates again and needs a new acknowledge.
            a.active = False
            a.message = str(rec["message"])
            a.acked = bool(rec["acked"]) and not bool(rec["active"])
            a.tripped = bool(rec["tripped"]) and a.latched
            a.first_out = bool(rec["first_out"]) and a.tripped
            a.acked_by = str(rec.get("acked_by", ""))
            since = rec.get("since_s")
            a.activated_t = now - float(since) if since is not None else None
            log.warning("alarm %s restored (%s): %s", a.id, a.state.value, a.message)

    def _restore_channel(self, channel: str, doc: Document) -> None:
        bench = self.bench
        db = bench.db
        # The whole document checked before anything of it is used (issue 26, finding 5):
        # a field that is not what the save writes refuses it, named with what it holds.
        unknown = sorted(set(doc) - {"channel", "chain", "recipe", "tags", "mode"})
        if unknown:
            raise ValueError(f"unknown field {', '.join(map(repr, unknown))}")
        if doc.get("channel", channel) != channel:
            raise ValueError(f"field channel: {shown(doc.get('channel'))} is not {channel!r}")
        tags = self._tag_values("tags", doc.get("tags"))
        mode_tag = db[f"{channel}.mode"]
        mode = doc.get("mode")
        choices = mode_tag.spec.choices or ()
        if mode is not None and mode not in choices:
            raise ValueError(f"field mode: {shown(mode)} is not one of {', '.join(choices)}")
        chain = doc.get("chain")
        snap = None if chain is None else ChainSnapshot.from_dict(chain)
        src = RecipeSource.from_dict(doc.get("recipe")) if doc.get("recipe") else None
        self._restore_tags(tags)
        if mode is not None:
            db.update(mode_tag, mode)
        if snap is None:
            return
        folder = Path(src.folder) if src is not None and src.folder else None
        away_s = max(0.0, bench.clock.wall() - snap.wall)
        if snap.state not in ACTIVE_VALUES:
            # The test had ended (or never started): Idle, its files closed.
            if folder is not None and folder.exists() and not ResultCollector.final_summary(folder):
                c = self._collector(channel, snap, folder, away_s)
                c.close(snap.end_reason or f"ended {snap.state}", snap.state)
            return
        if folder is not None and ResultCollector.final_summary(folder):
            log.info("%s: test %s had ended (final summary); starts Idle", channel, snap.test_id)
            return
        if src is None:
            raise ValueError("a test under way without its recipe")
        try:
            program = recipe_program(bench, channel, src)
        except (ConfigError, ConfigErrors) as exc:
            self._not_resumed(
                channel,
                snap,
                folder,
                away_s,
                f"recipe {snap.recipe} no longer compiles against {channel}: {_errors_text(exc)}",
            )
            return
        collector = self._collector(channel, snap, folder, away_s)
        bench.attach_results(channel, collector)
        try:
            away_s = bench.runners[channel].restore(snap, program)
        except ValueError as exc:
            bench.detach_results(channel)
            self._not_resumed(channel, snap, folder, away_s, str(exc), collector)
            return
        bench.recipes[channel] = src
        collector.checkpoint(State.HELD.value)
        line = (
            f"{channel}: test {snap.test_id} ({snap.recipe}) restored Held in step"
            f" {snap.step_id or snap.step + 1}, cycle {snap.cycle}, step time"
            f" {snap.step_time_s:.1f} s, after {away_s:.1f} s away; resume to continue"
        )
        log.warning("%s", line)
        self.report.append(line)

    def _collector(
        self, channel: str, snap: ChainSnapshot, folder: Path | None, away_s: float
    ) -> ResultCollector:
        collector = self.bench.new_collector(channel, snap.recipe, snap.test_id, folder)
        # Test time 0 on this process's clock axis: the time away counts as test time.
        collector.resume(self.bench.clock.now() - (snap.test_time_s + away_s))
        return collector

    def _not_resumed(
        self,
        channel: str,
        snap: ChainSnapshot,
        folder: Path | None,
        away_s: float,
        why: str,
        collector: ResultCollector | None = None,
    ) -> None:
        """The channel starts Idle; the test's folder and summary say why."""
        self._problem(f"{channel}: test {snap.test_id} not resumed after a restart: {why}")
        if folder is None:
            return
        c = collector or self._collector(channel, snap, folder, away_s)
        now = self.bench.clock.now()
        c.on_event(
            ChainEvent(
                now,
                self.bench.clock.to_wall(now),
                channel,
                "state",
                f"supervisor restarted after {away_s:.1f} s; test not resumed: {why}",
                snap.step,
                snap.step_id,
                snap.cycle,
            )
        )
        c.close(f"aborted: not resumed after a restart: {why}", State.ABORTED.value, now=now)

    # --- shutdown ----------------------------------------------------------------------
    def close(self) -> None:
        """Save everything once more and stop the writer (clean shutdown)."""
        for ch in sorted(self.bench.runners):
            self.store.put(f"channel:{ch}", self.channel_document(ch))
        self.store.put("alarms", self.alarms_document(self.bench.clock.now()))
        if self._bench_tags:
            self.store.put("tags", {"tags": {tag.name: tag.value for tag in self._bench_tags}})
        if not self.store.flush():
            log.error("retained state %s: last save failed: %s", self.store.path, self.store.error)
        self.store.close()


def _check_alarm(rec: Any) -> None:
    """One saved alarm as ``alarms_document`` writes it; ValueError naming the field."""
    if not isinstance(rec, dict):
        raise ValueError(f"alarms: {shown(rec)} is not an alarm record")
    for key in ("id", "message"):
        if not isinstance(rec.get(key), str):
            raise ValueError(f"alarms field {key}: {shown(rec.get(key))} is not a text")
    if not isinstance(rec.get("acked_by", ""), str):
        raise ValueError(f"alarms field acked_by: {shown(rec.get('acked_by'))} is not a text")
    for key in ("active", "acked", "tripped", "first_out"):
        if not isinstance(rec.get(key), bool):
            raise ValueError(f"alarms field {key}: {shown(rec.get(key))} is not true or false")
    since = rec.get("since_s")
    if since is not None and (
        isinstance(since, bool)
        or not isinstance(since, int | float)
        or not math.isfinite(since)
        or since < 0
    ):
        raise ValueError(f"alarms field since_s: {shown(since)} is not null or a time in s")


__all__ = ["RESTORE_ALARM", "TIMELINE_KINDS", "WRITE_ALARM", "RecipeSource", "Retention"]
