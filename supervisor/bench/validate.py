"""``supervisor bench validate-attack``: recipe texts a viewer posts to be validated never
cost the scan anything, and a check given up on is really stopped (issue 28, finding 2 and
its "Must show").

The attack of the issue, against a real ``supervisor run`` of io_maps/sim.yaml (the flood
bench's copy: free loopback ports, login on, a test running on ch0): three 150 KB recipe
texts posted at once by a viewer to ``/api/recipes/validate``, each a 140 KB condition
anchored once and aliased as the ``until`` of 100 steps (each alias is compiled again: a
minute of CPU each before the loader counted alias expansions). Before it took threads of
the supervisor: 503 after 30 s, but the threads ran on (100 % CPU, RSS 0.79 → 2.0 GB, 11
scan stalls, jitter p99 1.1 → 30 ms, SIGTERM 8–23 s). Now each check is a child process
with a deadline and a memory limit (``supervisor/commands/childjob.py``).

Figures, each with the same run's reference: the scan's stalls and its start jitter p99
(``scan.jitter_s`` sampled over HTTP about 20 times a second: a sample of the scans, not
every one) and the supervisor's resident memory (``VmRSS``) in a quiet window before the
attack and one after it; the answers (status, reason, seconds); the check processes left
running afterwards; then the time from SIGTERM to the process's exit, and whether it said
every output is safe. The machine's other load moves the timings (say so when quoting).
"""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from supervisor.bench.flood import (
    CHANNEL,
    OPERATOR,
    Client,
    Supervisor,
    add_user,
    bench_run,
    start_test,
    tag,
    wait_ready,
)

__all__ = [
    "VIEWER",
    "alias_text",
    "check_processes",
    "idle_check_processes",
    "validate_attack_benchmark",
    "vm_rss_bytes",
]

VIEWER: Final = ("vera", "vera-pw")
CHILD_MODULE: Final = "supervisor.commands.childjob"
POSTS: Final = 3
WINDOW_S: Final = 10.0
"""Each quiet window (before, after) the jitter is sampled over."""
ANSWER_WAIT_S: Final = 300.0
"""Upper bound for an answer (a hang is reported as such, not waited for ever)."""
EXIT_WAIT_S: Final = 60.0
MIB: Final = 1024 * 1024


def _say(msg: str) -> None:
    sys.stdout.write(msg + "\n")
    sys.stdout.flush()


def alias_text(total_bytes: int = 150_000, steps: int = 100) -> str:
    """A recipe of ``total_bytes``: one condition of nearly all of it anchored on the
    ``until`` of its first step and aliased as the ``until`` of ``steps - 1`` more."""
    unit = "voltage >= 1.5 V or "
    head = ["recipe: amplified", "capacity: 2 Ah", "steps:"]
    step = ["    charge: 0.1 A", "    duration: 1 h", "    until:"]
    rest = "".join(
        "\n".join([f"  - id: s{i}", *step, "      - *c : next"]) + "\n" for i in range(1, steps)
    )
    room = total_bytes - len("\n".join(head)) - len(rest) - 200
    cond = unit * max(1, room // len(unit)) + "voltage >= 1.6 V"
    first = ["  - id: s0", *step, f"      - ? &c {cond}", "        : next"]
    return "\n".join([*head, *first]) + "\n" + rest + "  - {id: done, end: true}\n"


def slow_text(steps: int = 2000) -> str:
    """A valid recipe of some 700 KB that takes seconds to check on any machine (2000 steps,
    each with its own condition of six comparisons — the compiler compiles a condition text
    once per recipe, so no two are alike): slow without any trick of YAML."""
    lines = ["recipe: slow", "capacity: 2 Ah", "cycles: 1", "steps:"]
    for s in range(steps):
        cond = " or ".join(
            f"(voltage >= {1.0 + (6 * s + i) / 1e5:.5f} V and current < {0.1 + i / 1000:.3f} A)"
            for i in range(6)
        )
        lines.append(
            f"  - id: s{s}\n    charge: 0.1 A\n    duration: 1 h\n    until:\n      - {cond}: next"
        )
    lines.append("  - {id: done, end: true}")
    return "\n".join(lines) + "\n"


# --- processes, from /proc ---------------------------------------------------------------------
def vm_rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise ValueError(f"no VmRSS for {pid}")


def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8")
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()  # [state, ppid, ...]


def check_processes(parent: int) -> dict[int, str]:
    """The live check processes (``python -m supervisor.commands.childjob``) of
    ``parent``: pid → state letter (R running, S sleeping; zombies left out)."""
    out: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        st = _stat(int(entry.name))
        if st is None or st[1] != str(parent) or st[0] in ("Z", "X"):
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if CHILD_MODULE.encode() in cmd:
            out[int(entry.name)] = st[0]
    return out


def idle_check_processes(parent: int, count: int, wait_s: float = 120.0) -> set[int]:
    """Once ``count`` check processes of ``parent`` sleep (ready: waiting for a job) on
    three polls in a row, their pids; ``TimeoutError`` after ``wait_s``."""
    deadline = time.monotonic() + wait_s
    calm = 0
    while True:
        procs = check_processes(parent)
        sleeping = {p for p, s in procs.items() if s == "S"}
        calm = calm + 1 if len(sleeping) >= count else 0
        if calm >= 3:
            return sleeping
        if time.monotonic() > deadline:
            raise TimeoutError(f"{count} check processes not ready: {procs}")
        time.sleep(0.2)


def gone(pid: int, wait_s: float = 30.0) -> bool:
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        st = _stat(pid)
        if st is None or st[0] in ("Z", "X"):
            return True
        time.sleep(0.05)
    return False


# --- the attack ----------------------------------------------------------------------------
@dataclass
class Answer:
    status: int
    reason: str
    seconds: float


@dataclass
class Window:
    stalls: int
    stall_max_s: float
    jitter_p99_s: float
    rss_bytes: int
    samples: int


@dataclass
class AttackFigures:
    before: Window | None = None
    after: Window | None = None
    during_jitter_p99_s: float = 0.0
    answers: list[Answer] = field(default_factory=list)
    ready_before: set[int] = field(default_factory=set)
    left_running: dict[int, str] = field(default_factory=dict)
    taken_gone: bool = False
    exit_s: float = 0.0
    exit_code: int | None = None
    safe: bool = False
    realtime: bool = False


def _p99(xs: list[float]) -> float:
    if not xs:
        return float("nan")
    s = sorted(xs)
    return s[min(len(s) - 1, round(0.99 * (len(s) - 1)))]


def _sample_jitter(c: Client, stop: threading.Event, until_s: float | None = None) -> list[float]:
    out: list[float] = []
    end = None if until_s is None else time.monotonic() + until_s
    while not stop.is_set() and (end is None or time.monotonic() < end):
        v = tag(c, "scan.jitter_s")
        if isinstance(v, int | float):
            out.append(float(v))
        time.sleep(0.05)
    return out


def _window(sup: Supervisor, c: Client) -> Window:
    jit = _sample_jitter(c, threading.Event(), WINDOW_S)
    return Window(
        int(tag(c, "scan.stalls")),
        float(tag(c, "scan.stall_max_s") or 0.0),
        _p99(jit),
        vm_rss_bytes(sup.proc.pid),
        len(jit),
    )


def viewer(sup: Supervisor) -> Client:
    c = Client(sup.host, sup.http_port, timeout_s=ANSWER_WAIT_S)
    status, body = c.call("POST", "/api/login", {"user": VIEWER[0], "password": VIEWER[1]})
    assert status == 200, body
    return c


def post_at_once(sup: Supervisor, text: str, posts: int = POSTS) -> list[Answer]:
    """``posts`` validations of ``text`` by a viewer, each on its own connection, sent
    together; their answers."""
    clients = [viewer(sup) for _ in range(posts)]
    answers: list[Answer | None] = [None] * posts
    go = threading.Barrier(posts)

    def one(i: int) -> None:
        go.wait()
        t0 = time.monotonic()
        try:
            status, body = clients[i].call("POST", "/api/recipes/validate", {"text": text})
            reason = str((body or {}).get("reason", "")) if isinstance(body, dict) else ""
        except Exception as exc:  # a hang or a reset: reported, not raised
            status, reason = -1, f"no answer: {exc!r}"
        answers[i] = Answer(status, reason, time.monotonic() - t0)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(posts)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for c in clients:
        c.close()
    return [a for a in answers if a is not None]


def sigterm(sup: Supervisor) -> tuple[float, int | None, str]:
    """SIGTERM by pid: seconds to its exit, its exit code, what it printed since start."""
    t0 = time.monotonic()
    os.kill(sup.proc.pid, signal.SIGTERM)
    try:
        out, _ = sup.proc.communicate(timeout=EXIT_WAIT_S)
    except Exception:
        os.kill(sup.proc.pid, signal.SIGKILL)
        out, _ = sup.proc.communicate()
    return time.monotonic() - t0, sup.proc.returncode, out or ""


def attack(sup: Supervisor, text: str, workers: int) -> AttackFigures:
    fig = AttackFigures()
    op = Client(sup.host, sup.http_port)
    status, body = op.call("POST", "/api/login", {"user": OPERATOR[0], "password": OPERATOR[1]})
    assert status == 200, body
    wait_ready(op)
    start_test(op)
    fig.ready_before = idle_check_processes(sup.proc.pid, workers)
    fig.before = _window(sup, op)
    stop = threading.Event()
    during: list[float] = []
    sampler = threading.Thread(target=lambda: during.extend(_sample_jitter(op, stop)))
    sampler.start()
    try:
        fig.answers = post_at_once(sup, text)
    finally:
        stop.set()
        sampler.join()
    fig.during_jitter_p99_s = _p99(during)
    fig.taken_gone = all(gone(p) for p in fig.ready_before)
    # The after window once the new waiting processes are ready (their imports done): the
    # steady state the attack left, not the start of its replacements.
    idle_check_processes(sup.proc.pid, workers)
    fig.after = _window(sup, op)
    status, diag = op.call("GET", "/api/diagnostics")
    fig.realtime = bool(status == 200 and diag["scan"].get("realtime_priority"))
    # Busy ones too (R): a new waiting process importing is not expected 10 s later.
    fig.left_running = {
        p: s for p, s in check_processes(sup.proc.pid).items() if p in fig.ready_before or s == "R"
    }
    assert tag(op, f"{CHANNEL}.chain.state") == "Running"
    op.close()
    fig.exit_s, fig.exit_code, out = sigterm(sup)
    fig.safe = "stopped: all outputs safe" in out
    return fig


def report(fig: AttackFigures) -> list[str]:
    assert fig.before is not None and fig.after is not None
    b, a = fig.before, fig.after
    lines = [
        f"validate attack: {len(fig.answers)} posts of a 150 KB alias-amplified recipe by a"
        " viewer to /api/recipes/validate, at once",
    ]
    for i, ans in enumerate(fig.answers):
        lines.append(f"  answer {i + 1}: HTTP {ans.status} after {ans.seconds:.1f} s: {ans.reason}")
    lines += [
        f"  scan stalls:         before {b.stalls}, after {a.stalls}"
        f" (+{a.stalls - b.stalls}; stall_max_s {a.stall_max_s:.3f})",
        f"  start jitter p99:    before {b.jitter_p99_s * 1000:.2f} ms, during"
        f" {fig.during_jitter_p99_s * 1000:.2f} ms, after {a.jitter_p99_s * 1000:.2f} ms"
        f" ({b.samples}/{a.samples} samples of scan.jitter_s; the scan's real-time"
        f" priority: {'yes' if fig.realtime else 'no'})",
        f"  supervisor VmRSS:    before {b.rss_bytes / MIB:.1f} MiB, after"
        f" {a.rss_bytes / MIB:.1f} MiB ({(a.rss_bytes - b.rss_bytes) / MIB:+.1f} MiB)",
        f"  check processes:     the {len(fig.ready_before)} ready before all gone:"
        f" {'yes' if fig.taken_gone else 'NO'}; still running: {fig.left_running or 'none'}",
        f"  SIGTERM → exit:      {fig.exit_s:.2f} s, exit code {fig.exit_code},"
        f" {'all outputs safe' if fig.safe else 'safe state NOT reported'}",
    ]
    return lines


def validate_attack_benchmark(timeout_s: float | None = None) -> int:
    from supervisor.bench.report import record
    from supervisor.config.limits import RECIPE_CHECK_WORKERS

    recipes: dict[str, Any] = {} if timeout_s is None else {"check_timeout_s": timeout_s}
    with (
        tempfile.TemporaryDirectory(prefix="bench-validate-") as tmp,
        bench_run(Path(tmp), recipes=recipes) as sup,
    ):
        add_user(Path(tmp) / "flood.yaml", *VIEWER, role="viewer")
        fig = attack(sup, alias_text(), RECIPE_CHECK_WORKERS)
    for line in report(fig):
        _say(line)
    assert fig.before is not None and fig.after is not None
    cmd = "supervisor bench validate-attack"
    ref = "the same run before the attack"
    stalls = fig.after.stalls - fig.before.stalls
    rss_mib = (fig.after.rss_bytes - fig.before.rss_bytes) / MIB
    record("validate attack: scan stalls", stalls, "", "== 0", ref, cmd)
    record("validate attack: supervisor RSS growth", rss_mib, "MiB", "< 50", ref, cmd)
    record(
        "validate attack: jitter p99 after",
        fig.after.jitter_p99_s * 1000,
        "ms",
        f"reference {fig.before.jitter_p99_s * 1000:.2f}",
        ref,
        cmd,
    )
    record("validate attack: SIGTERM to exit", fig.exit_s, "s", "< 2", "", cmd)
    ok = (
        stalls == 0
        and rss_mib < 50
        and fig.taken_gone
        and not fig.left_running
        and fig.safe
        and all(a.status in (413, 422, 503) for a in fig.answers)
    )
    return 0 if ok else 1
