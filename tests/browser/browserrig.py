"""The HMI's browser test rig: a real ``supervisor run`` on a copy of io_maps/sim.yaml (free
loopback ports, a temporary state directory, demo users) and Debian's Chromium driven by
Playwright (``executable_path=/usr/bin/chromium``, headless; Playwright never downloads a
browser here). Both are stopped at teardown, the supervisor by its pid."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.cookiejar import CookieJar
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = ROOT / "tests" / "artifacts"
SCREENS = ARTIFACTS / "screens"
FIGURES = ARTIFACTS / "hmi-figures.json"
VIEWPORT = {"width": 1366, "height": 768}  # the panel PC of issue 12
SHORT_RECIPE = Path(__file__).resolve().parent / "short-cycle.yaml"

# Demo users of the test bench (role = name), as `make run` creates them.
USERS = {"viewer": "viewer-pw", "operator": "operator-pw", "engineer": "engineer-pw"}

START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(
    what: str, pred: Callable[[], Any], timeout_s: float = 20.0, poll_s: float = 0.1
) -> Any:
    """``pred()``'s first truthy answer, or AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        last = pred()
        if last:
            return last
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what} (last: {last!r})")


def hmi_options() -> set[str]:
    """The ``hmi:`` keys this supervisor's I/O map accepts (login, session timeout, ...)."""
    from supervisor.config.models import HmiConfig

    return set(HmiConfig.model_fields)


def bench_map(workdir: Path, **hmi: Any) -> Path:
    """io_maps/sim.yaml on free loopback ports with its state and recipes under
    ``workdir``, login on when the supervisor has it."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    for name in ("adam", "ea", "bms"):
        data["devices"][name]["port"] = free_port()
    known = hmi_options()
    wanted = {"login": True, **hmi}
    data["hmi"] = {
        **data.get("hmi", {}),
        "port": 0,
        **{k: v for k, v in wanted.items() if k in known},
    }
    # OPC UA off (not what this tests; 4840 may be taken); the recipes folder, which the
    # HMI's Recipes screen shares, is a copy: a test that saves never writes into recipes/.
    recipes = workdir / "recipes"
    recipes.mkdir(exist_ok=True)
    for src in [*(ROOT / "recipes").glob("*.yaml"), SHORT_RECIPE]:
        shutil.copy(src, recipes / src.name)
    data["opcua"] = {"enabled": False}
    data.pop("modbus_server", None)
    data["recipes"] = {"folders": [str(recipes)]}
    data["state_dir"] = str(workdir / "state")
    path = workdir / "sim.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def create_users(state_dir: Path) -> None:
    """The users of the bench, in the OPC UA users file the HMI shares."""
    from supervisor.config.users import add_user

    users_file = state_dir / "opcua" / "users.yaml"
    users_file.parent.mkdir(parents=True, exist_ok=True)
    for name, password in USERS.items():
        add_user(users_file, name, name, password)


@dataclass
class Supervisor:
    """A ``supervisor run`` we started; ``base`` is its page (``http://127.0.0.1:port``)."""

    proc: subprocess.Popen[str]
    base: str
    workdir: Path
    log_path: Path
    login: bool
    drain: threading.Thread
    jars: dict[str, urllib.request.OpenerDirector] = field(default_factory=dict)

    @property
    def state_dir(self) -> Path:
        return self.workdir / "state"

    def opener(self, user: str | None) -> urllib.request.OpenerDirector:
        """An HTTP client with its own cookie jar, logged in as ``user`` (None: anonymous)."""
        key = user or ""
        if key not in self.jars:
            opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(CookieJar()))
            self.jars[key] = opener
            if user and self.login:
                status, body = self._call(
                    opener, "POST", "/api/login", {"user": user, "password": USERS[user]}
                )
                assert status == 200, f"login {user}: {status} {body}"
        return self.jars[key]

    def call(
        self, method: str, path: str, body: Any = None, user: str | None = "operator"
    ) -> tuple[int, Any]:
        return self._call(self.opener(user), method, path, body)

    def _call(
        self, opener: urllib.request.OpenerDirector, method: str, path: str, body: Any
    ) -> tuple[int, Any]:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.base + path, data=data, method=method)
        # Every command declares JSON, a body or not (supervisor.hmi.csrf).
        req.add_header("Content-Type", "application/json")
        try:
            with opener.open(req, timeout=10) as res:
                return res.status, json.loads(res.read() or b"null")
        except urllib.error.HTTPError as err:
            raw = err.read()
            try:
                return err.code, json.loads(raw or b"null")
            except ValueError:
                return err.code, raw.decode(errors="replace")

    def tag(self, name: str) -> Any:
        status, body = self.call("GET", f"/api/tags/{name}")
        assert status == 200, f"GET {name}: {status} {body}"
        return body["value"]

    def log_tail(self, lines: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(encoding="utf-8").splitlines()[-lines:])
        except OSError:
            return ""


def start_supervisor(workdir: Path, **hmi: Any) -> Supervisor:
    workdir.mkdir(parents=True, exist_ok=True)
    path = bench_map(workdir, **hmi)
    create_users(workdir / "state")
    log_path = workdir / "supervisor.log"
    log_file = log_path.open("a", encoding="utf-8")  # a restart appends
    exe = [sys.executable, "-m", "supervisor.cli.main"]
    if (Path(sys.executable).parent / "supervisor").exists():
        exe = [str(Path(sys.executable).parent / "supervisor")]
    proc = subprocess.Popen(
        [*exe, "run", str(path), "--log-level", "warning"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=log_file,
        text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    log_file.close()
    base = ""
    assert proc.stdout is not None
    deadline = time.monotonic() + START_TIMEOUT_S
    lines: list[str] = []
    for line in proc.stdout:
        lines.append(line.rstrip("\n"))
        if line.startswith("HTTP API listening on "):
            base = line.split()[-1].removesuffix("/api/tags")
        if line.startswith("Ctrl-C") or time.monotonic() > deadline:
            break
    if not base:
        stop(proc)
        proc.stdout.close()
        tail = log_path.read_text(encoding="utf-8")[-3000:]
        raise AssertionError(f"supervisor run did not start: {lines}\n{tail}")
    # The rest of stdout goes to a file (a full pipe would block the supervisor).
    drain = threading_drain(proc, workdir / "supervisor.stdout")
    login = "login" in hmi_options() and hmi.get("login", True) is not False
    sup = Supervisor(proc, base, workdir, log_path, login, drain)
    wait_for(
        "the simulated devices connected",
        lambda: all(sup.tag(t) is True for t in ("adam.connected", "ea.connected", "estop.ok")),
        timeout_s=30,
    )
    log.info("supervisor pid %d on %s", proc.pid, base)
    return sup


def threading_drain(proc: subprocess.Popen[str], path: Path) -> threading.Thread:
    def drain() -> None:
        assert proc.stdout is not None
        with path.open("w", encoding="utf-8") as out:
            for line in proc.stdout:
                out.write(line)

    thread = threading.Thread(target=drain, name=f"stdout-{proc.pid}", daemon=True)
    thread.start()
    return thread


def stop(proc: subprocess.Popen[str]) -> None:
    """Stop the supervisor we started, by its pid: SIGTERM (outputs safe), then SIGKILL."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()


def stop_supervisor(sup: Supervisor) -> None:
    stop(sup.proc)
    sup.drain.join(STOP_TIMEOUT_S)  # at the end of its output once the process ended
    if sup.proc.stdout is not None:
        sup.proc.stdout.close()


def supervisor_fixture(workdir: Path, **hmi: Any) -> Iterator[Supervisor]:
    sup = start_supervisor(workdir, **hmi)
    try:
        yield sup
    finally:
        stop_supervisor(sup)


def screenshot(page: Any, name: str) -> Path:
    """A full-page screenshot under tests/artifacts/screens/, its path printed."""
    SCREENS.mkdir(parents=True, exist_ok=True)
    path = SCREENS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    print(f"screenshot: {path.relative_to(ROOT)}")
    return path


def save_figures(update: dict[str, Any]) -> None:
    """Merge measured figures into tests/artifacts/hmi-figures.json."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    figures: dict[str, Any] = {}
    if FIGURES.exists():
        try:
            figures = json.loads(FIGURES.read_text(encoding="utf-8"))
        except ValueError:
            figures = {}
    figures.update(update)
    FIGURES.write_text(json.dumps(figures, indent=2) + "\n", encoding="utf-8")
    print(f"figures: {FIGURES.relative_to(ROOT)}")


def login(page: Any, bench: Supervisor, user: str, where: str = "#/") -> None:
    """Open ``where`` and log in as ``user`` on the login screen (if the bench has login)."""
    # A full load (a page already on the HMI would only change its hash, and the login
    # screen found could be the one about to be replaced).
    page.goto("about:blank")
    page.goto(f"{bench.base}/{where}")
    if bench.login:
        page.wait_for_function("() => location.hash.startsWith('#/login')")
        page.wait_for_selector("#login-form")
        page.fill("#login-user", user)
        page.fill("#login-password", USERS[user])
        page.click("#login-submit")
    page.wait_for_selector("#top:not([hidden])")


def result_text(page: Any, selector: str = "#cmd-result") -> str:
    """The answer a command's result line shows, once it is complete (not the "…" of one
    under way)."""
    page.wait_for_selector(f"{selector}:not([hidden])")
    page.wait_for_function(
        "(sel) => { const t = document.querySelector(sel).textContent;"
        " return t && !t.endsWith('…'); }",
        arg=selector,
    )
    return str(page.text_content(selector))
