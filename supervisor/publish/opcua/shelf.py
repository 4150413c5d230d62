"""The OPC UA standard address space kept in a shelf file (docs/adr/0020-opcua-aspace-shelf.md).

asyncua builds the standard address space (namespace 0: about 6000 nodes, every type,
``Server`` object and data type the specification defines) as Python objects at each
start: about 50 MB of the supervisor's resident memory, while a bench's clients touch a
few hundred of those nodes. Given a shelf (``Server.init(shelf_file=...)``), asyncua reads
a node from the file the first time something asks for it and keeps it from then on.

The shelf depends only on asyncua's version and on the Python that pickled it, so one per
(asyncua, Python) pair is shared by every bench and process of the machine, in the user's
cache folder (:func:`cache_dir`). Built once, in a child process (the parent never holds
the whole space), into a private temporary folder that is then renamed into place: the
rename is atomic, so concurrent first starts each build one and the first rename wins; a
reader never sees a half-written shelf. A shelf is never written again after that
(asyncua opens it read-only).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Final

log = logging.getLogger(__name__)

CACHE_ENV: Final = "SUPERVISOR_CACHE_DIR"
"""Overrides the cache folder (tests, a read-only home)."""
SHELF_ENV: Final = "SUPERVISOR_OPCUA_SHELF"
"""``0``: no shelf, the standard address space in memory as asyncua builds it by default."""
NAME: Final = "aspace"
BUILD_TIMEOUT_S: Final = 120.0
"""Building it takes about 3 s of CPU (measured on the 2-core bench machine)."""
STALE_BUILD_S: Final = 3600.0
"""A temporary build folder older than this was left by a process that died building."""


def cache_dir() -> Path:
    """Where shelves live: ``$SUPERVISOR_CACHE_DIR``; systemd's ``$CACHE_DIRECTORY``
    (``CacheDirectory=`` of deploy/bench-supervisor@.service, the home being protected);
    else ``$XDG_CACHE_HOME/bench-supervisor`` or ``~/.cache/bench-supervisor``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    if os.environ.get("CACHE_DIRECTORY"):  # systemd: possibly several, colon-separated
        return Path(os.environ["CACHE_DIRECTORY"].split(":")[0])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "bench-supervisor"


def shelf_key() -> str:
    """What the shelf's content depends on: asyncua's version (its standard address space
    and classes) and Python's (the pickle protocol, the dbm module)."""
    v = sys.version_info
    return f"opcua-aspace-asyncua-{metadata.version('asyncua')}-py{v.major}.{v.minor}"


def shelf_path(root: Path | None = None) -> Path:
    """The path to hand ``Server.init`` (the shelf's files are next to it)."""
    return (root or cache_dir()) / shelf_key() / NAME


def ready(path: Path) -> bool:
    """The shelf at ``path`` is complete: its folder exists only once it was renamed in."""
    return (path.parent / "complete").is_file()


Maker = Callable[[Path], None]
"""Writes a shelf at the path it is given (:func:`make_in_child`; tests give their own)."""


async def ensure_shelf(root: Path | None = None, make: Maker | None = None) -> Path | None:
    """The shared shelf, built first when there is none yet; None when there is none and
    none can be made (no shelf wanted, a read-only cache, a failed build): the caller then
    lets asyncua build the space in memory, as without a shelf."""
    if os.environ.get(SHELF_ENV, "1") == "0":
        return None
    path = shelf_path(root)
    if ready(path):
        return path
    try:
        await asyncio.to_thread(build_shelf, path, make)
    except (OSError, subprocess.SubprocessError, RuntimeError) as exc:
        log.warning(
            "OPC UA: no shelf for the standard address space (%s): it is built in memory", exc
        )
        return None
    return path if ready(path) else None


def make_in_child(path: Path) -> None:
    """Write the shelf ``path`` in a child process: the whole space is built there, so
    this process's memory never holds it (a Python process rarely gives freed memory back)."""
    done = subprocess.run(
        [sys.executable, "-m", __name__, str(path)],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=BUILD_TIMEOUT_S,
        check=False,
    )
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"building it failed ({done.returncode}): {last}")


def build_shelf(path: Path, make: Maker | None = None) -> None:
    """Build the shelf ``path`` (by default in a child process), then rename it into place
    (another process may have been faster: then its shelf is kept and this one dropped)."""
    final = path.parent
    final.parent.mkdir(parents=True, exist_ok=True)
    _drop_stale_builds(final.parent)
    tmp = Path(tempfile.mkdtemp(prefix=f".build-{final.name}-", dir=final.parent))
    try:
        t0 = time.monotonic()
        (make or make_in_child)(tmp / NAME)
        for f in tmp.iterdir():  # on disk before the rename makes it visible
            with f.open("rb") as fh:
                os.fsync(fh.fileno())
        (tmp / "complete").write_text(f"{shelf_key()}\n", encoding="utf-8")
        try:
            tmp.rename(final)
        except OSError:
            if not ready(path):
                raise
            log.info("OPC UA: shelf %s built by another process meanwhile", final)
        else:
            log.info(
                "OPC UA: standard address space shelved in %s (%.1f s)",
                final,
                time.monotonic() - t0,
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _drop_stale_builds(root: Path) -> None:
    now = time.time()
    for p in root.glob(".build-*"):
        with contextlib.suppress(OSError):
            if now - p.stat().st_mtime > STALE_BUILD_S:
                shutil.rmtree(p, ignore_errors=True)


async def _make(path: Path) -> None:
    """The child's work: asyncua fills the standard address space and, given a shelf path
    that does not exist yet, writes it there (what its next starts load)."""
    from asyncua.server.internal_server import InternalServer

    await InternalServer().load_standard_address_space(path)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        sys.stderr.write("usage: python -m supervisor.publish.opcua.shelf PATH\n")
        return 2
    path = Path(argv[0])
    asyncio.run(_make(path))
    if not path.exists() and not path.with_suffix(".db").exists():
        # dbm.dumb (the only dbm of a Python built without gdbm/ndbm) writes PATH.dat and
        # PATH.dir; asyncua looks for PATH or PATH.db before it loads a shelf.
        path.touch()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
