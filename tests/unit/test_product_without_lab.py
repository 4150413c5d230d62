"""The product without its lab (issue 29, finding 5): the benchmarks, fault injection and
load generators live in ``supervisor.bench``, which only the command line (``supervisor
bench``, ``run``'s memory tracing switch) and the test helpers import. pyproject's
import-linter contract "The product never imports its lab" says the same to ``make lint``;
this test says it to the suite."""

from __future__ import annotations

import grimp

# What may import the lab: the lab itself, the command line and the test helpers.
LAB_USERS = ("supervisor.bench", "supervisor.cli", "supervisor.testing")


def test_no_module_of_the_product_imports_the_lab_directly_or_through_another() -> None:
    graph = grimp.build_graph("supervisor", cache_dir=None)
    importers = graph.find_downstream_modules("supervisor.bench", as_package=True)
    product = sorted(m for m in importers if not m.startswith(LAB_USERS))
    assert product == []
