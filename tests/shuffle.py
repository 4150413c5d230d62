"""The tests in another order, to find a test whose result depends on what ran before it
in the same process (issue 29, finding 11): ``pytest -p tests.shuffle --shuffle-seed=N``
shuffles the modules, then the tests within each module (as pytest-randomly does, which
this project does not install); ``--reverse-order`` runs every test in reverse. The same
seed gives the same order in every pytest-xdist worker, as xdist requires."""

from __future__ import annotations

import random

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("shuffle")
    group.addoption("--shuffle-seed", type=int, default=None, help="shuffle with this seed")
    group.addoption("--reverse-order", action="store_true", help="run the tests in reverse")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--reverse-order"):
        items.reverse()
        return
    seed = config.getoption("--shuffle-seed")
    if seed is None:
        return
    rng = random.Random(seed)
    by_module: dict[str, list[pytest.Item]] = {}
    for item in items:
        by_module.setdefault(item.nodeid.split("::", 1)[0], []).append(item)
    modules = list(by_module.values())
    rng.shuffle(modules)
    items[:] = []
    for tests in modules:
        rng.shuffle(tests)
        items.extend(tests)


def pytest_report_header(config: pytest.Config) -> str | None:
    seed = config.getoption("--shuffle-seed")
    if config.getoption("--reverse-order"):
        return "tests in reverse order (tests/shuffle.py)"
    return f"tests shuffled with seed {seed} (tests/shuffle.py)" if seed is not None else None
