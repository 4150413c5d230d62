"""Loading a recipe never stops the scan (issue 9): read, parsed and compiled in a worker
thread, with a time limit; only the compiled program is applied on the event loop.

The same command path either way (ADR 0008): ``execute_async`` (the HTTP API, ``supervisor
run --recipe``) compiles in a worker thread, ``execute`` compiles in place where no scan
runs; both give the same answers. The slow compile here is a real one held on an event, so
what runs while it waits is certain, not a matter of timing; the bench is on the virtual
clock.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import logging
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from commandrig import CV_ON_CHADECHE, DISCHARGE, recipe

import supervisor.commands.path as command_path
from supervisor.app import Bench
from supervisor.commands import (
    Command,
    PreparedRecipe,
    Result,
    ResultKind,
    Verb,
    compile_recipe_file,
)
from supervisor.testing import run_scans

ROOT = Path(__file__).resolve().parents[2]
LIMIT_MESSAGE = (
    "file is too large: more than 1 MiB; a recipe may have at most 1 MiB (README: Input limits)"
)


def load(channel: str = "ch0", **args: Any) -> Command:
    return Command.channel(channel, Verb.LOAD, "operator", **args)


class HeldCompile:
    """Wraps the real compile: records the thread it ran on, and waits for ``release``."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()
        self.threads: list[threading.Thread] = []
        self.real: Callable[..., PreparedRecipe] = command_path.compile_recipe_file

    def __call__(self, *args: Any, **kw: Any) -> PreparedRecipe:
        self.threads.append(threading.current_thread())
        self.started.set()
        assert self.release.wait(10.0), "the test never released the compile"
        return self.real(*args, **kw)


@pytest.fixture
def held(monkeypatch: pytest.MonkeyPatch) -> Iterator[HeldCompile]:
    h = HeldCompile()
    monkeypatch.setattr(command_path, "compile_recipe_file", h)
    try:
        yield h
    finally:
        h.release.set()  # never leave a worker waiting


async def started(bench: Bench, command: Command, held: HeldCompile) -> asyncio.Task[Result]:
    task = asyncio.create_task(bench.commands.execute_async(command))
    assert await asyncio.to_thread(held.started.wait, 10.0), "the compile never started"
    return task


async def test_the_recipe_is_compiled_in_a_worker_thread_while_the_scan_goes_on(
    bench: Bench, tmp_path: Path, held: HeldCompile
) -> None:
    scans = bench.db["scan.count"].value
    task = await started(bench, load(recipe=recipe(tmp_path)), held)
    await run_scans(bench.engine, 10)  # the compile is still held: the scan runs anyway
    assert bench.db["scan.count"].value == scans + 10  # type: ignore[operator]
    assert not task.done() and bench.runners["ch0"].program is None
    held.release.set()
    result = await task
    assert result.accepted, result
    assert bench.runners["ch0"].program is not None
    assert held.threads and held.threads[0] is not threading.main_thread()


async def test_a_load_over_its_time_limit_is_refused_and_its_late_result_dropped(
    bench: Bench, tmp_path: Path, held: HeldCompile, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, "supervisor.commands.worker")
    bench.commands.compile_timeout_s = 0.05
    file = recipe(tmp_path)
    result = await bench.commands.execute_async(load(recipe=file))
    assert not result.accepted and result.kind is ResultKind.TIMEOUT
    assert result.http_status == 503
    assert result.reason == (
        f"ch0: recipe refused: reading and compiling {file} took more than 0.05 s;"
        " the load is abandoned (README: Input limits)"
    )
    held.release.set()  # the worker ends now; what it compiled is dropped
    await asyncio.to_thread(held.threads[0].join, 10.0)
    await asyncio.sleep(0.01)  # its result's callback has had its turn on the loop
    assert bench.runners["ch0"].program is None
    assert f"loading {file} on ch0: finished after its time limit; result dropped" in caplog.text
    assert bench.commands.log[-1].text.endswith(result.reason)
    bench.commands.compile_timeout_s = 30.0
    assert (await bench.commands.execute_async(load(recipe=file))).accepted  # the slot is free


async def test_a_second_load_on_a_channel_waits_for_the_first_one_s_answer(
    bench: Bench, tmp_path: Path, held: HeldCompile
) -> None:
    first = await started(bench, load(recipe=recipe(tmp_path, name="a.yaml")), held)
    second = await bench.commands.execute_async(load(recipe=recipe(tmp_path, name="b.yaml")))
    assert not second.accepted and second.kind is ResultKind.REFUSED
    assert (
        second.reason == f"ch0: recipe {tmp_path / 'a.yaml'} is being loaded: wait for its answer"
    )
    # Another channel is not held up by it.
    other = asyncio.create_task(
        bench.commands.execute_async(load("ch1", recipe=recipe(tmp_path, name="c.yaml")))
    )
    held.release.set()
    assert (await first).accepted and (await other).accepted


@pytest.mark.parametrize("asynchronous", [False, True], ids=["execute", "execute_async"])
async def test_dev_zero_is_refused_by_its_size_before_it_is_read(
    bench: Bench, asynchronous: bool
) -> None:
    # Given in the shell (`supervisor run --recipe ch0=/dev/zero`): over the network it is
    # refused before, as outside the recipe folders (test_recipe_folders.py).
    command = dataclasses.replace(load(recipe="/dev/zero"), local=True)
    if asynchronous:
        result = await bench.commands.execute_async(command)
    else:
        result = bench.commands.execute(command)
    assert not result.accepted and result.kind is ResultKind.INVALID_RECIPE
    assert result.reason == f"ch0: recipe refused: /dev/zero: {LIMIT_MESSAGE}"
    assert result.http_status == 422


@pytest.mark.parametrize("asynchronous", [False, True], ids=["execute", "execute_async"])
async def test_a_20_mb_recipe_is_refused_by_its_size(
    bench: Bench, tmp_path: Path, asynchronous: bool
) -> None:
    big = tmp_path / "big.yaml"
    with big.open("w", encoding="utf-8") as f:
        f.write("recipe: big\nsteps:\n")
        f.write("  - {id: s, rest: 1 s}\n" * 900_000)  # 20.7 MB
    command = load(recipe=str(big))
    result = (
        await bench.commands.execute_async(command)
        if asynchronous
        else bench.commands.execute(command)
    )
    size = big.stat().st_size
    assert result.reason == (
        f"ch0: recipe refused: {big}: file is too large: {size:,} bytes; a recipe may have at"
        " most 1 MiB (README: Input limits)"
    )


def without_test_id(result: Result) -> tuple[object, ...]:
    return (result.accepted, result.kind, result.reason.split(" (test ")[0], result.details)


async def test_both_ways_give_the_same_answers_and_records(bench: Bench, tmp_path: Path) -> None:
    bad = recipe(tmp_path, CV_ON_CHADECHE)
    missing = str(tmp_path / "nope.yaml")
    good = recipe(tmp_path, DISCHARGE, "g.yaml")
    kinds = []
    for file in (bad, missing, good):
        in_place = bench.commands.execute(load(recipe=file))
        in_worker = await bench.commands.execute_async(load(recipe=file))
        assert without_test_id(in_place) == without_test_id(in_worker)
        kinds.append(in_place.kind)
    assert kinds == [ResultKind.INVALID_RECIPE, ResultKind.NOT_FOUND, ResultKind.ACCEPTED]
    recorded = [e.text.split(" by ")[0] for e in bench.commands.log][-6:]
    assert recorded == [f"load {f}" for f in (bad, bad, missing, missing, good, good)]


async def test_start_with_a_recipe_compiles_it_in_the_worker_too(
    bench: Bench, tmp_path: Path, held: HeldCompile
) -> None:
    command = Command.channel("ch0", Verb.START, "operator", recipe=recipe(tmp_path))
    task = await started(bench, command, held)
    held.release.set()
    result = await task
    assert result.accepted, result
    assert held.threads[0] is not threading.main_thread()
    await run_scans(bench.engine, 5)
    assert bench.db["ch0.current_cmd"].value == pytest.approx(-0.2)


def test_compiling_loading_and_replacing_programs_makes_no_reference_cycles(
    bench: Bench, tmp_path: Path
) -> None:
    """What lets the worker freeze the heap after a load (``commands/worker.py``): a
    program, the document it came from and the one it replaces are all freed by reference
    counting, none left for the garbage collector."""
    files = [
        str(ROOT / "recipes" / "nimh-ds2710.yaml"),  # conditions, parameters, gotos
        recipe(tmp_path, DISCHARGE),
        str(ROOT / "recipes" / "nimh-ds2710.yaml"),
    ]
    gc.collect()
    gc.disable()
    try:
        for file in files:
            prepared = compile_recipe_file("ch0", file, bench.target("ch0"))
            bench.install_recipe(prepared)
            del prepared
        unreachable = gc.collect()
    finally:
        gc.enable()
    assert unreachable == 0
