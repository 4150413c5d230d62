"""Wire the notifications into a bench: the I/O map's ``notifications:`` section → a
``Notifier`` listening to the alarm model and the step chains, publishing its counts at
scan end (``supervisor.notify``; docs/notifications.md)."""

from __future__ import annotations

from supervisor.app.bench import Bench
from supervisor.notify import Notifier

__all__ = ["build_notifier"]


def build_notifier(bench: Bench) -> Notifier | None:
    """The bench's notifier (None without a ``notifications:`` section); not started."""
    cfg = bench.cfg
    if cfg.notifications is None:
        return None
    notifier = Notifier(
        cfg.notifications,
        cfg.bench,
        bench.clock,
        cfg.state_dir,
        db=bench.db,
        alarms=bench.alarms,
    )
    if bench.alarms is not None:
        bench.alarms.listeners.append(notifier.on_alarm)
    for name, runner in bench.runners.items():
        runner.listeners.append(notifier.chain_listener(name))
    bench.engine.publishers.append(notifier)  # its tags and alarm at scan end
    return notifier
