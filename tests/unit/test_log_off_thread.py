"""``supervisor run`` logs through a queue: the scan's thread hands a record over and a
thread of its own formats and writes it (a write to stderr is a system call that lets the
interpreter lock go, issue 13); nothing queued is lost at a normal exit."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import logging, sys, threading, time
class Recorder:
    def __init__(self):
        self.threads = set()
    def write(self, text):
        self.threads.add(threading.current_thread().name)
        sys.__stdout__.write(text)
    def flush(self):
        pass
recorder = Recorder()
sys.stderr = recorder
from supervisor.cli.main import _setup_logging
_setup_logging("info", off_thread=OFF_THREAD)
logging.getLogger("supervisor.chains.engine").info("ch0: starting step charge")
deadline = time.monotonic() + 10
while not recorder.threads and time.monotonic() < deadline:
    time.sleep(0.01)
print("writers:", sorted(recorder.threads))
logging.getLogger("supervisor").warning("the last line before the exit")
"""


def run(off_thread: bool) -> str:
    code = SCRIPT.replace("OFF_THREAD", str(off_thread))
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    return done.stdout


def test_supervisor_runs_log_lines_are_written_by_a_thread_of_their_own() -> None:
    out = run(off_thread=True)
    assert "INFO    supervisor.chains.engine: ch0: starting step charge" in out
    assert "writers: ['MainThread']" not in out and "writers: [" in out
    # Queued at the exit, written before the process ended.
    assert out.rstrip().endswith("WARNING supervisor: the last line before the exit")


def test_the_other_commands_write_their_log_lines_at_once() -> None:
    assert "writers: ['MainThread']" in run(off_thread=False)
