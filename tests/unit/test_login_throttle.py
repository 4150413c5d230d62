"""Failed logins throttled per user and per address (issue 27, finding 4), on injected
time: progressive bounded delays, another user or another address unaffected, a user's
own panel never locked by an attacker elsewhere, counts forgotten after a quiet spell, the
burst that raises ``security.login_burst``; and an unknown user costs the same password
hash as a known one (counted, never timed)."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.config import users as users_module
from supervisor.config.users import UserStore, add_user
from supervisor.core.logins import ADDRESS, FORGET_S, PAIR, USER, LoginThrottle

A, B = "10.0.0.1", "10.0.0.2"


class Now:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def fail(throttle: LoginThrottle, user: str, address: str, n: int) -> None:
    for _ in range(n):
        assert throttle.refusal(user, address) is None
        throttle.failed(user, address)


def test_failures_beyond_the_limit_lock_the_user_at_the_address_for_a_doubling_bounded_delay() -> (
    None
):
    now = Now()
    throttle = LoginThrottle(now)
    fail(throttle, "otto", A, PAIR.free - 1)
    assert throttle.refusal("otto", A) is None  # the last free try
    throttle.failed("otto", A)
    delays = []
    for _ in range(10):
        refusal = throttle.refusal("otto", A)
        assert refusal is not None
        assert "too many failed logins for this user from this address: try again in" in (
            refusal.reason
        )
        delays.append(refusal.retry_after_s)
        now.t += refusal.retry_after_s
        fail(throttle, "otto", A, 1)
    assert delays == [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 60.0, 60.0, 60.0, 60.0]


def test_a_lockout_leaves_another_user_and_the_same_user_elsewhere_alone() -> None:
    throttle = LoginThrottle(Now())
    fail(throttle, "otto", A, PAIR.free)
    assert throttle.refusal("otto", A) is not None
    assert throttle.refusal("erin", A) is None  # another user from the same address
    assert throttle.refusal("otto", B) is None  # the same user from another address


def test_a_success_clears_the_users_count_at_that_address_only() -> None:
    throttle = LoginThrottle(Now())
    fail(throttle, "otto", A, PAIR.free - 1)
    throttle.succeeded("otto", A)
    fail(throttle, "otto", A, PAIR.free - 1)
    assert throttle.refusal("otto", A) is None


def test_one_address_spraying_user_names_is_locked_for_every_name() -> None:
    throttle = LoginThrottle(Now())
    for i in range(ADDRESS.free):
        fail(throttle, f"guess{i}", A, 1)
    refusal = throttle.refusal("otto", A)
    assert refusal is not None and "for this address" in refusal.reason
    assert throttle.refusal("otto", B) is None


def test_guesses_from_elsewhere_never_lock_a_user_out_of_an_address_they_logged_in_from() -> None:
    now = Now()
    throttle = LoginThrottle(now)
    throttle.succeeded("otto", A)  # the operator's panel
    # Guesses at otto's password spread over many addresses (each under its own limit).
    for i in range(USER.free):
        fail(throttle, "otto", f"10.1.0.{i}", 1)
    assert throttle.refusal("otto", "10.1.0.99") is not None  # the user's limit
    assert throttle.refusal("otto", A) is None
    # From an address otto never used the user is locked, briefly and boundedly.
    refusal = throttle.refusal("otto", B)
    assert refusal is not None and "for this user:" in refusal.reason
    assert refusal.retry_after_s <= USER.max_s
    now.t += USER.max_s
    assert throttle.refusal("otto", B) is None


def test_counts_are_forgotten_after_a_quiet_spell() -> None:
    now = Now()
    throttle = LoginThrottle(now)
    fail(throttle, "otto", A, PAIR.free - 1)
    now.t += FORGET_S
    fail(throttle, "otto", A, PAIR.free - 1)
    assert throttle.refusal("otto", A) is None


def test_a_burst_of_failed_or_refused_tries_is_seen_until_a_window_after_it_stops() -> None:
    now = Now()
    throttle = LoginThrottle(now, burst_tries=10, burst_window_s=60.0)
    fail(throttle, "otto", A, PAIR.free)
    assert throttle.burst() == ""
    for _ in range(5):  # refused tries count too: a flood refused is still a flood
        assert throttle.refusal("otto", A) is not None
    assert "10 or more failed or refused logins within 60 s" in throttle.burst()
    now.t += 59.0
    assert throttle.burst() != ""
    now.t += 2.0
    assert throttle.burst() == ""


def test_the_tables_stay_bounded_whatever_names_are_sprayed() -> None:
    now = Now()
    throttle = LoginThrottle(now, max_entries=50)
    for i in range(1000):
        throttle.failed("x" * 1000 + str(i), f"10.2.{i // 256}.{i % 256}")
    assert all(len(t.counts) <= 50 for t in (throttle._pair, throttle._address, throttle._user))


@pytest.fixture
def users(tmp_path: Path) -> UserStore:
    path = tmp_path / "users.yaml"
    add_user(path, "otto", "operator", "otto-pw")
    return UserStore(path)


def test_an_unknown_user_costs_the_same_password_hash_as_a_known_one(
    users: UserStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    runs: list[int] = []
    scrypt = users_module._scrypt

    def counted(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
        runs.append(n)
        return scrypt(password, salt, n, r, p)

    monkeypatch.setattr(users_module, "_scrypt", counted)
    users.authenticate("nobody", "warm-up")  # the first unknown name also makes the dummy
    runs.clear()
    assert users.authenticate("otto", "wrong") is None
    known = list(runs)
    runs.clear()
    assert users.authenticate("mallory", "wrong") is None
    assert runs == known == [users_module.SCRYPT_N]  # one scrypt each, the same parameters
    assert users.checks == 3  # the store's own count: one hash per unknown or wrong try
