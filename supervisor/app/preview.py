"""The HMI's dry-run preview (``POST /api/recipes/dryrun``), computed in a child process.

Not in a thread of the supervisor: a dry run is pure Python that runs flat out for
seconds, and a thread of it holds the interpreter's lock in 5 ms slices against the scan's
event loop, which gives the lock up at every socket read and waits up to a slice to get it
back. Measured on the simulated bench (io_maps/sim.yaml, 0.1 s scan): during a dry run of
the 25 h NiMH recipe in a worker thread the scan skipped 12 deadlines and the e-stop sense
went stale (tests/integration/test_hmi_recipes_api.py). A child process has its own lock
and, in the idle scheduling class, gives way to the scan at once on a busy machine.

A recipe previewed for a channel runs on that channel's own plant (:class:`ChannelPreviews`:
the child reads the bench's I/O map again and simulates the channel's supply, battery and
sensors, ``dry_run(io_map=…, channel=…)``), not on the built-in NiMH board: a ch4 recipe
was refused "channel ch0 allows [-0.4, 0.4] A" (issue 32).

The child (``python -m supervisor.app.preview``) reads one JSON job on stdin and writes one
JSON answer on stdout: the dry run's end, its summary and a trace of at most
``MAX_TRACE_POINTS`` points, or the recipe's errors. It stops itself at its time limit
(between two chunks of virtual time, answering what it has); the parent kills it if it has
not answered a grace period later.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from supervisor.app.dryrun import dry_run
from supervisor.config.models import BenchConfig
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.registry import load_bench
from supervisor.hmi.recipes_api import Trace

log = logging.getLogger(__name__)

__all__ = ["ChannelPreviews", "PreviewFailed", "preview_in_child", "previews_of"]

GRACE_S: Final = 15.0
"""How long after its time limit the parent waits for the child's answer (it stops at the
end of the chunk under way, then shuts its bench down) before killing it."""
NICENESS: Final = 19
"""Where there is no idle scheduling class: the lowest priority (``nice``)."""


class PreviewFailed(Exception):
    """The child did not answer (killed at its time limit, crashed): the reason."""


def _error_json(e: ConfigError) -> dict[str, Any]:
    return {"message": e.message, "file": e.file, "line": e.line, "col": e.col}


def _io_map(job: Mapping[str, Any]) -> BenchConfig | None:
    """The running supervisor's I/O map, read again from its file: refused when the file
    changed since the supervisor loaded it (the preview would not show this bench)."""
    path = job.get("io_map")
    if not path or job.get("channel") is None:
        return None
    cfg = load_bench(path)
    if job.get("io_map_sha256") and cfg.source_sha256 != job["io_map_sha256"]:
        raise ConfigError(
            "the I/O map changed since the supervisor loaded it: the preview cannot show the"
            " channel's plant as it runs (restart the supervisor to use the new map)",
            path,
        )
    return cfg


async def _run(job: Mapping[str, Any]) -> dict[str, Any]:
    deadline = time.monotonic() + float(job["timeout_s"])
    trace = Trace()
    try:
        io_map = _io_map(job)
        res = await dry_run(
            job["file"],
            text=job["text"],
            params=dict(job.get("params") or {}),
            capacity_ah=job.get("capacity_ah"),
            max_hours=float(job["max_hours"]),
            recorders=(trace,),
            should_stop=lambda: time.monotonic() > deadline,
            io_map=io_map,
            channel=job.get("channel") if io_map is not None else None,
        )
    except ConfigErrors as exc:
        return {"errors": [_error_json(e) for e in exc.errors]}
    except ConfigError as exc:
        return {"errors": [_error_json(exc)]}
    return {
        "recipe": res.program.name,
        "end_reason": res.end_reason,
        "finished": res.finished,
        "simulated_s": res.simulated_s,
        "timed_out": not res.finished and time.monotonic() > deadline,
        "summary": res.summary,
        "trace": trace.as_json(),
    }


def _lowest_priority() -> None:
    """Run only on CPU time nothing else wants (Linux ``SCHED_IDLE``: a waking scan takes
    the core at once), else at the lowest ``nice``: a preview may be slow, the scan may not
    be late."""
    idle = getattr(os, "SCHED_IDLE", None)
    if idle is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, idle, os.sched_param(0))
            return
    with contextlib.suppress(OSError):
        os.nice(NICENESS)


def child_main() -> int:
    """The child's entry: a job on stdin, the answer on stdout."""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    _lowest_priority()
    job = json.loads(sys.stdin.read())
    answer = asyncio.run(_run(job))
    sys.stdout.write(json.dumps(answer, allow_nan=False) + "\n")
    return 0


@dataclass(frozen=True)
class ChannelPreviews:
    """The previews of one bench (:class:`~supervisor.hmi.recipes_api.DryRunner`): a recipe
    for a channel runs on that channel's own plant, simulated from the bench's I/O map
    (``io_map``, the file the supervisor loaded; its SHA-256 as loaded); without a channel,
    or without a file (a bench built in code), on the built-in dry-run bench."""

    io_map: str = ""
    io_map_sha256: str = ""

    async def __call__(
        self,
        file: str,
        text: str,
        params: Mapping[str, str],
        capacity_ah: float | None,
        max_hours: float,
        timeout_s: float,
        channel: str | None = None,
    ) -> dict[str, Any]:
        return await preview_in_child(
            file,
            text,
            params,
            capacity_ah,
            max_hours,
            timeout_s,
            channel,
            io_map=self.io_map,
            io_map_sha256=self.io_map_sha256,
        )


def previews_of(cfg: BenchConfig) -> ChannelPreviews:
    """The previews of the bench ``cfg`` describes (the composition root's)."""
    return ChannelPreviews(cfg.source_file, cfg.source_sha256)


async def preview_in_child(
    file: str,
    text: str,
    params: Mapping[str, str],
    capacity_ah: float | None,
    max_hours: float,
    timeout_s: float,
    channel: str | None = None,
    *,
    io_map: str = "",
    io_map_sha256: str = "",
) -> dict[str, Any]:
    """The preview's answer (see :func:`_run`); ``PreviewFailed`` when none came.
    ``channel`` with ``io_map``: on that channel's plant (:class:`ChannelPreviews`)."""
    job = {
        "file": file,
        "text": text,
        "params": dict(params),
        "capacity_ah": capacity_ah,
        "max_hours": max_hours,
        "timeout_s": timeout_s,
        "channel": channel,
        "io_map": io_map,
        "io_map_sha256": io_map_sha256,
    }
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "supervisor.app.preview",
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        out, err = await asyncio.wait_for(
            proc.communicate(json.dumps(job).encode("utf-8")), timeout_s + GRACE_S
        )
    except TimeoutError:
        raise PreviewFailed(
            f"the dry run of {file} did not answer within {timeout_s + GRACE_S:g} s; stopped"
        ) from None
    finally:
        if proc.returncode is None:  # timed out, or the request went away (cancelled)
            proc.kill()
            await proc.wait()
    if proc.returncode != 0:
        why = err.decode("utf-8", "replace").strip().splitlines()[-1:] or ["no message"]
        log.error("dry run of %s: child exited %s: %s", file, proc.returncode, err.decode())
        raise PreviewFailed(f"the dry run of {file} failed: {why[0]}")
    answer: dict[str, Any] = json.loads(out)
    return answer


if __name__ == "__main__":
    sys.exit(child_main())
