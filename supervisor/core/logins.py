"""Password guessing slowed down: failed logins throttled per user and per client address
(issue 27, finding 4; OWASP Authentication Cheat Sheet, "Login Throttling").

One ``LoginThrottle`` per bench, shared by every door that checks a password (the HMI's
``POST /api/login`` and OPC UA's UserName tokens): a guesser gains nothing by switching
from one to the other. Three counts of failed tries, each with a progressive delay:

- per **(user, address)**: ``PAIR`` — 5 failures free, then each failure locks that user
  at that address for 1 s, 2 s, 4 s ... at most 60 s;
- per **address** (any user: one host spraying user names): ``ADDRESS`` — 20 failures
  free, then the same doubling delay, at most 60 s;
- per **user** (any address: guesses spread over hosts): ``USER`` — 20 failures free, then
  the same doubling delay, at most 60 s, **except** at an address the user has logged in
  from since the bench started: an attacker elsewhere cannot lock the operator out of
  their own panel, at most out of a new one, for at most a minute at a time.

A count is forgotten ``FORGET_S`` (15 min) after its last failure; a success clears the
(user, address) count only (a guesser holding one valid account must not reset the
address's count by logging in with it between two guesses). While a delay runs every try
is refused **without checking the password**, the right one too (else the delay would not
slow anything): HTTP answers 429 with ``Retry-After``, OPC UA Bad_UserAccessDenied.

Failed and refused tries are also counted bench-wide: ``BURST_TRIES`` (20) of them within
``BURST_WINDOW_S`` (60 s) is a burst (``burst()``: the alarm ``security.login_burst``,
raised and cleared by the scan), over one minute after the tries stop.

Thread-safe: HTTP calls it on the scan's loop, OPC UA on the server's own thread. Times are
the bench clock's ``now`` (virtual in tests). Memory is bounded: at most ``MAX_ENTRIES``
counts per table (the oldest go first) and ``KNOWN_PER_USER`` addresses per user.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

FORGET_S: Final = 900.0
"""A count of failures is forgotten this long after its last failure."""
MAX_ENTRIES: Final = 4096
"""Counts kept per table at most (names sprayed by a guesser must not grow the process)."""
KNOWN_PER_USER: Final = 8
"""Addresses remembered per user as places they logged in from."""
BURST_TRIES: Final = 20
BURST_WINDOW_S: Final = 60.0
MAX_NAME_CHARS: Final = 64
"""User names are cut to this in the tables (no user's name is longer)."""


@dataclass(frozen=True, slots=True)
class Rule:
    """``free`` failures, then each further failure locks for ``base_s`` doubling up to
    ``max_s``."""

    free: int
    base_s: float = 1.0
    max_s: float = 60.0
    what: str = ""

    def delay_s(self, failures: int) -> float:
        if failures < self.free:
            return 0.0
        return min(self.max_s, self.base_s * 2.0 ** min(failures - self.free, 30))


PAIR: Final = Rule(5, what="this user from this address")
ADDRESS: Final = Rule(20, what="this address")
USER: Final = Rule(20, what="this user")


@dataclass(slots=True)
class _Count:
    failures: int = 0
    last_t: float = -math.inf
    locked_until: float = -math.inf


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why a try is refused before its password is checked, and for how long."""

    retry_after_s: float
    reason: str


class _Table:
    def __init__(self, rule: Rule, forget_s: float, max_entries: int) -> None:
        self.rule = rule
        self.forget_s = forget_s
        self.max_entries = max_entries
        self.counts: OrderedDict[object, _Count] = OrderedDict()

    def _live(self, key: object, now: float) -> _Count | None:
        c = self.counts.get(key)
        if c is not None and now - c.last_t >= self.forget_s and now >= c.locked_until:
            del self.counts[key]
            return None
        return c

    def wait_s(self, key: object, now: float) -> float:
        c = self._live(key, now)
        return 0.0 if c is None else max(0.0, c.locked_until - now)

    def fail(self, key: object, now: float) -> None:
        c = self._live(key, now) or _Count()
        c.failures += 1
        c.last_t = now
        delay = self.rule.delay_s(c.failures)
        if delay > 0:
            c.locked_until = max(c.locked_until, now + delay)
        self.counts[key] = c
        self.counts.move_to_end(key)
        while len(self.counts) > self.max_entries:
            self.counts.popitem(last=False)

    def clear(self, key: object) -> None:
        self.counts.pop(key, None)


class LoginThrottle:
    """The bench's failed-login counts (see the module's text for the rules)."""

    def __init__(
        self,
        now: Callable[[], float],
        *,
        pair: Rule = PAIR,
        address: Rule = ADDRESS,
        user: Rule = USER,
        forget_s: float = FORGET_S,
        max_entries: int = MAX_ENTRIES,
        burst_tries: int = BURST_TRIES,
        burst_window_s: float = BURST_WINDOW_S,
    ) -> None:
        self._now = now
        self._lock = threading.Lock()
        self._pair = _Table(pair, forget_s, max_entries)
        self._address = _Table(address, forget_s, max_entries)
        self._user = _Table(user, forget_s, max_entries)
        self._known: OrderedDict[str, OrderedDict[str, None]] = OrderedDict()
        self.burst_tries = burst_tries
        self.burst_window_s = burst_window_s
        # The times of the last ``burst_tries`` failed or refused tries: a burst when the
        # oldest of them is within the window.
        self._recent: deque[float] = deque(maxlen=burst_tries)
        self.failed_tries = 0
        self.refused_tries = 0

    @staticmethod
    def _keys(user: str, address: str) -> tuple[str, str]:
        return user[:MAX_NAME_CHARS], address or "?"

    def refusal(self, user: str, address: str) -> Refusal | None:
        """None when ``user`` may try a password from ``address`` now; else how long to wait
        (the try counts toward a burst)."""
        name, addr = self._keys(user, address)
        with self._lock:
            now = self._now()
            waits = [
                (self._pair.wait_s((name, addr), now), self._pair.rule),
                (self._address.wait_s(addr, now), self._address.rule),
            ]
            if addr not in self._known.get(name, ()):
                waits.append((self._user.wait_s(name, now), self._user.rule))
            wait_s, rule = max(waits, key=lambda w: w[0])
            if wait_s <= 0:
                return None
            self.refused_tries += 1
            self._recent.append(now)
        seconds = max(1, math.ceil(wait_s))
        return Refusal(
            wait_s,
            f"too many failed logins for {rule.what}: try again in {seconds} s",
        )

    def failed(self, user: str, address: str) -> None:
        """A wrong password (or an unknown user) from ``address``."""
        name, addr = self._keys(user, address)
        with self._lock:
            now = self._now()
            self._pair.fail((name, addr), now)
            self._address.fail(addr, now)
            self._user.fail(name, now)
            self.failed_tries += 1
            self._recent.append(now)

    def succeeded(self, user: str, address: str) -> None:
        """The right password: clears this (user, address) count and remembers ``address``
        as one of the user's places."""
        name, addr = self._keys(user, address)
        with self._lock:
            self._pair.clear((name, addr))
            known = self._known.setdefault(name, OrderedDict())
            self._known.move_to_end(name)
            known[addr] = None
            known.move_to_end(addr)
            while len(known) > KNOWN_PER_USER:
                known.popitem(last=False)
            while len(self._known) > self._pair.max_entries:
                self._known.popitem(last=False)

    def burst(self) -> str:
        """ "" when there is no burst of failed logins now; else what it is."""
        with self._lock:
            now = self._now()
            if len(self._recent) < self.burst_tries:
                return ""
            if now - self._recent[0] > self.burst_window_s:
                return ""
            return (
                f"{self.burst_tries} or more failed or refused logins within"
                f" {self.burst_window_s:g} s (password guessing?)"
            )
