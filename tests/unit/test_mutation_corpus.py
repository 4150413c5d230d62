"""The mutation corpus in process: a mutated file is refused at its place, or accepted.

A hypothesis sample of each class of ``tests/mutation.py`` (the small profile: no files of
megabytes) through ``supervisor.cli.main.main`` with stdout and stderr captured, as a user
would run ``supervisor check FILE`` or ``supervisor import chadeche FILE [--prm P]``
(docs/operator.md "Commands": one clear message naming file, line and column, exit code 2, never a
traceback), and a certainly invalid variant is never accepted. The sample is fixed
(``derandomize``): ``make test`` runs the same variants every time. The full run, in
subprocesses with a time limit, is ``make mutation`` (``tests/mutation_run.py``).

A variant labelled ``pending`` waits for a fix on another branch of issue 9 (zero-time loops,
count limits): it is held to a clean outcome (no traceback) but may still be accepted.
A failure names its variant; ``python -m tests.mutation_run --show INDEX --only CLASS
--small`` writes it to ``var/mutation/variants/``.
"""

from __future__ import annotations

import contextlib
import io
import signal
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mutation import (
    BYTE_LIMIT,
    MUTATIONS,
    ROOT,
    SOURCES,
    Source,
    Variant,
    Verdict,
    _Doc,
    classify,
    make_variant,
)

from supervisor.cli.main import main

# Generous CPU budget per command (a hang detector, not a speed claim): these files are at
# most a few hundred kB and take milliseconds; a spin shows as a failure naming its variant
# instead of the whole test being stopped by pytest-timeout without saying which one.
CPU_BUDGET_S = 60.0
# The sample is small files: the work is bounded by the input (a bound in bytes, no clock).
MAX_SAMPLE_BYTES = 512 * 1024

SMALL = sorted(name for name, m in MUTATIONS.items() if not m.large)


class CpuBudgetExceeded(BaseException):
    """Raised in the command when it used more CPU than CPU_BUDGET_S (a spin, a hang)."""


@contextlib.contextmanager
def _cpu_budget(seconds: float) -> Iterator[None]:
    def expired(signum: int, frame: FrameType | None) -> None:
        raise CpuBudgetExceeded(f"more than {seconds:g} s of CPU")

    previous = signal.signal(signal.SIGPROF, expired)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)


@dataclass(frozen=True)
class Run:
    variant: Variant
    code: int | None
    stderr: str
    escaped: BaseException | None
    verdict: Verdict

    def explain(self) -> str:
        return (
            f"{self.variant.label()}\nexpect {self.variant.expect}; exit {self.code},"
            f" {self.verdict.outcome} {self.verdict.why}\nescaped: {self.escaped!r}\n"
            f"stderr:\n{self.stderr[:2000]}"
        )


def run_in_process(variant: Variant) -> Run:
    """The variant through ``main()`` as the command line would run it."""
    assert len(variant.content) <= MAX_SAMPLE_BYTES, variant.label()
    with tempfile.TemporaryDirectory(prefix="mutation-") as tmp:
        feed = variant.write(Path(tmp))
        out, err = io.StringIO(), io.StringIO()
        code: int | None = None
        escaped: BaseException | None = None
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                with _cpu_budget(CPU_BUDGET_S):
                    code = main(feed.argv)
            except SystemExit as exc:  # argparse
                code = exc.code if isinstance(exc.code, int) else 2
            except (Exception, CpuBudgetExceeded) as exc:
                escaped = exc
        stderr = err.getvalue()
        verdict = classify(
            1 if escaped else code,
            stderr,
            feed.files,
            via=feed.via,
            whole_file=variant.whole_file,
        )
        return Run(variant, code, stderr, escaped, verdict)


_SAMPLE = settings(
    max_examples=8,
    deadline=None,  # no wall-clock bound: a hang is the CPU budget's or pytest-timeout's
    database=None,
    derandomize=True,  # the same sample on every run: `make test` stays reproducible
    suppress_health_check=[HealthCheck.too_slow],
)


@pytest.mark.parametrize("mutation", SMALL)
@_SAMPLE
@given(index=st.integers(min_value=0, max_value=10**6))
def test_a_mutated_file_is_refused_at_its_place_or_accepted_never_a_certain_error_accepted(
    mutation: str, index: int
) -> None:
    variant = make_variant(index, mutation=mutation, small=True)
    run = run_in_process(variant)
    assert run.escaped is None, run.explain()
    assert run.code in (0, 2), run.explain()
    assert run.verdict.outcome in ("accepted", "located", "file_only"), run.explain()
    if variant.expect == "refuse" and not variant.pending:
        assert run.code == 2, run.explain()


# --- the generator and the classification themselves -----------------------------------------


def _accepts(src: Source, tmp: Path) -> tuple[int | None, str]:
    variant = Variant(0, 0, "none", "unmutated", src.path, src.target, src.data, "either")
    run = run_in_process(variant) if len(src.data) <= MAX_SAMPLE_BYTES else None
    assert run is not None
    return run.code, run.stderr


@pytest.mark.parametrize(
    "src",
    [s for s in SOURCES if not Path(s.path).name.startswith("bad")],
    ids=lambda s: s.path,
)
def test_every_valid_source_is_accepted_as_it_is(src: Source, tmp_path: Path) -> None:
    """A mutation starts from a file the command accepts (the bad-* corpus files aside)."""
    code, err = _accepts(src, tmp_path)
    assert code == 0, err


def test_variants_are_reproducible_from_their_index() -> None:
    """A failure is replayed from its index alone (``python -m tests.mutation_run --show``)."""
    for index in range(0, 300, 7):
        a, b = make_variant(index), make_variant(index)
        assert (a.mutation, a.how, a.content, a.expect) == (b.mutation, b.how, b.content, b.expect)


def test_every_class_makes_variants_with_a_label() -> None:
    for name in MUTATIONS:
        variant = make_variant(0, mutation=name, small=not MUTATIONS[name].large)
        assert variant.mutation == name
        assert variant.how, name


def test_a_variant_over_its_byte_limit_is_certainly_refused_as_a_whole_file() -> None:
    variants = (make_variant(i, mutation="size.huge_text") for i in range(40))
    over = next(v for v in variants if len(v.content) > BYTE_LIMIT[v.target])
    assert (over.expect, over.whole_file, over.pending) == ("refuse", True, "")
    under = make_variant(0, mutation="text.tabs")
    assert not under.whole_file


def test_unmutated_yaml_written_back_loads_as_the_original() -> None:
    """The node-graph round trip changes nothing but the mutated node."""
    for src in SOURCES:
        if src.target == "check":
            assert yaml.safe_load(_Doc(src.text).emit()) == yaml.safe_load(src.text), src.path


@pytest.mark.parametrize(
    ("code", "stderr", "whole_file", "outcome"),
    [
        (0, "", False, "accepted"),
        (2, "f.yaml:3:5: steps[0]: unknown key\n", False, "located"),
        (2, "f.yaml:3:5: one\nf.yaml:9:1: two\n", False, "located"),
        (2, "f.yaml:3: no column\n", False, "unlocated"),
        (2, "f.yaml: file is too large\n", False, "unlocated"),
        (2, "f.yaml: file is too large\n", True, "file_only"),
        (2, "other.yaml:3:5: names another file\n", False, "unlocated"),
        (2, "f.yaml:3:5: located\nthen a bare line\n", False, "unlocated"),
        (2, "", False, "unlocated"),
        (2, "Traceback (most recent call last):\n  ...\nValueError: x\n", False, "traceback"),
        (0, "Traceback (most recent call last):\n", False, "traceback"),
        (1, "error\n", False, "traceback"),
        (-9, "", False, "traceback"),
        (None, "", False, "timeout"),
    ],
)
def test_classify_tells_each_outcome(
    code: int | None, stderr: str, whole_file: bool, outcome: str
) -> None:
    assert classify(code, stderr, ["f.yaml"], whole_file=whole_file).outcome == outcome


def test_classify_takes_the_position_of_the_recipe_naming_a_profile_first() -> None:
    line = "r.yaml:4:21: p.csv:3:1: time '６0' is not a number\n"
    assert classify(2, line, ["p.csv"], via=["r.yaml"]).outcome == "located"
    # ... but the message must still locate the profile itself
    assert classify(2, "r.yaml:4:21: bad\n", ["p.csv"], via=["r.yaml"]).outcome == "unlocated"


def test_the_source_files_are_under_the_project() -> None:
    assert all((ROOT / s.path).is_file() for s in SOURCES)
    assert {s.target for s in SOURCES} == {"check", "chadeche", "prm", "profile"}
