"""Debian's Mosquitto on a free loopback port, for ``supervisor bench fleet`` and the tests'
rig (tests/mqttrig.py): a configuration of its own (anonymous; no persistence unless asked),
stopped by its pid, never a service of the machine (``make mosquitto`` installs the
package)."""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import time
from pathlib import Path
from typing import Final

from supervisor.bench.ports import LOOPBACK, free_port
from supervisor.bench.processes import stop_with_parent

__all__ = ["Broker", "mosquitto_binary"]

START_TIMEOUT_S: Final = 15.0
DEBIAN_MOSQUITTO: Final = Path("/usr/sbin/mosquitto")


def mosquitto_binary() -> Path:
    found = shutil.which("mosquitto") or (
        str(DEBIAN_MOSQUITTO) if DEBIAN_MOSQUITTO.exists() else None
    )
    if found is None:
        raise RuntimeError("mosquitto is not installed: `make mosquitto` (Debian package)")
    return Path(found)


class Broker:
    """One Mosquitto on 127.0.0.1:<free port>, its configuration and log under ``root``."""

    def __init__(self, root: Path, persistent: bool = False) -> None:
        """``persistent``: the broker keeps its clients' sessions across a restart, QoS 0
        messages included (queued for a session whose client is away)."""
        root.mkdir(parents=True, exist_ok=True)
        self.binary = mosquitto_binary()
        self.root = root
        self.port = free_port()
        self.url = f"mqtt://{LOOPBACK}:{self.port}"
        self.log = root / "mosquitto.log"
        self.config = root / "mosquitto.conf"
        keep = (
            f"persistence true\npersistence_location {root}/\nqueue_qos0_messages true\n"
            if persistent
            else "persistence false\n"
        )
        # max_queued_messages 0: no limit, so a burst of a hundred nodes' births is not cut
        # at the default 1000 queued messages of a slow subscriber (the fleet).
        # Run as whoever started it: Mosquitto started by root otherwise becomes the user
        # "mosquitto", which cannot write its log and persistence file under ``root``
        # (found when a persistent broker kept no session across its restart).
        self.config.write_text(
            f"user {pwd.getpwuid(os.getuid()).pw_name}\n"
            f"listener {self.port} {LOOPBACK}\nallow_anonymous true\n{keep}"
            f"max_queued_messages 0\nlog_dest file {self.log}\n"
            "log_type error\nlog_type warning\nlog_type notice\n",
            encoding="utf-8",
        )
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def start(self) -> None:
        """Start it (again, on the same port and configuration after a stop)."""
        if self.running:
            return
        self.proc = subprocess.Popen(
            [str(self.binary), "-c", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL,
            preexec_fn=stop_with_parent(),  # no broker left behind by a killed run
        )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self._accepts():
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self.proc.returncode}: {self.log}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"mosquitto did not listen in {START_TIMEOUT_S:g} s")
            time.sleep(0.05)

    def _accepts(self) -> bool:
        try:
            with socket.create_connection((LOOPBACK, self.port), timeout=1):
                return True
        except OSError:
            return False

    def stop(self) -> None:
        """SIGTERM by pid, SIGKILL when it does not stop in 10 s."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
