"""Every dry run ends with a clear message, in bounded memory (issue 9).

A run that reaches ``--max-hours`` says so, with the cap and where it was (step, cycle,
test time), instead of a predicted duration, and ``supervisor dry-run`` exits 1; the
timeline, the step sequence and the per-cycle figures keep their first and last halves
(``DRY_RUN_EVENTS_KEPT``, ``DRY_RUN_CYCLES_KEPT``) and count the rest; result files
stream every row to disk. All on the virtual clock; no timing is asserted.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from supervisor.app.dryrun import DryRunResult, dry_run, format_report
from supervisor.chains.states import State
from supervisor.cli.main import build_parser, main
from supervisor.config.limits import DRY_RUN_CYCLES_KEPT, DRY_RUN_EVENTS_KEPT
from supervisor.publish.results import (
    CYCLES_SUFFIX,
    LIVE_CYCLES_KEPT,
    LIVE_EVENTS_KEPT,
    TIMELINE_SUFFIX,
    FirstAndLast,
    ResultCollector,
    read_jsonl,
)

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_recipes"

NEVER_TRUE = """recipe: never-true
steps:
  - id: wait
    rest: true
    until:
      - voltage >= 5 V: next
"""
MILLION_CYCLES = """recipe: million-cycles
cycles: 1000000
steps:
  - {id: tick, rest: 1 s}
"""


def write(tmp_path: Path, text: str, name: str = "r.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def report(res: DryRunResult) -> str:
    return "\n".join(format_report(res))


# --- the cap --------------------------------------------------------------------------------
async def test_an_until_that_never_comes_true_stops_at_the_cap_saying_where(
    tmp_path: Path,
) -> None:
    res = await dry_run(write(tmp_path, NEVER_TRUE), max_hours=2)
    assert not res.finished
    assert res.state is State.RUNNING
    assert res.end_reason == (
        "did not finish within 2 h (--max-hours): at test time 2:00:00 in step 'wait'"
        " (1 of 1) of cycle 1 of 1, after 1 step start; step 'wait' has no duration and"
        " none of its until conditions came true in 2:00:00"
    )
    assert res.simulated_s == pytest.approx(2 * 3600, abs=2.0)  # where it stopped, not 0
    lines = format_report(res)
    assert "predicted duration: did not finish within 2 h" in lines
    assert not any(line.startswith("predicted duration: 0:00:00") for line in lines)
    assert f"end: Running: {res.end_reason}" in lines
    assert res.summary["end_reason"] == res.end_reason


async def test_a_finished_run_still_predicts_its_duration(tmp_path: Path) -> None:
    text = "recipe: r\nsteps:\n  - {id: a, rest: 90 s}\n"
    res = await dry_run(write(tmp_path, text), max_hours=2)
    assert res.finished and res.state is State.COMPLETE
    assert "predicted duration: 0:01:30 (0.03 h)" in format_report(res)


def test_the_cli_exits_1_when_the_run_did_not_finish(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dry-run", str(write(tmp_path, NEVER_TRUE)), "--max-hours", "1"]) == 1
    captured = capsys.readouterr()
    assert "predicted duration: did not finish within 1 h\n" in captured.out
    assert "end: Running: did not finish within 1 h (--max-hours): at test time 1:00:00" in (
        captured.out
    )
    assert "Traceback" not in captured.err


def test_the_help_documents_the_default_cap_and_the_exit_codes() -> None:
    sub = build_parser()._subparsers._group_actions[0]  # type: ignore[union-attr]
    dry = sub.choices["dry-run"]  # type: ignore[attr-defined]
    text = " ".join(dry.format_help().split())
    assert "(default 1000 h; exit 1)" in text
    assert "exit codes: 0 the recipe came to an end" in text
    assert "1 it did not finish within --max-hours" in text
    assert "2 a usage or recipe error" in text
    assert dry.parse_args(["r.yaml"]).max_hours == 1000.0


@pytest.mark.parametrize(
    "name", ["zero_rest_loop.yaml", "until_true_at_once.yaml", "zero_cycle_body.yaml"]
)
def test_a_zero_time_loop_is_refused_before_the_dry_run_starts(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dry-run", str(BAD / name)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "loop that lets no time pass" in captured.err and "Traceback" not in captured.err


# --- the runs that never ended ------------------------------------------------------
def test_a_huge_initial_charge_ends_with_one_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The input limit on initial_charge refuses it (exit 2, its place named); without it
    # the run ends at the cap (exit 1) saying where: either way one message, no traceback.
    text = (
        "recipe: r\ninitial_charge: 1e300 Ah\nsteps:\n  - id: discharge\n    discharge: 200 mA\n"
        "    until:\n      - charge <= 0.1 Ah: next\n"
    )
    code = main(["dry-run", str(write(tmp_path, text)), "--max-hours", "1"])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    if code == 1:
        assert "end: Running: did not finish within 1 h (--max-hours)" in captured.out
        assert "step 'discharge' has no duration" in captured.out
    else:
        assert code == 2 and "initial_charge" in captured.err


async def test_an_initial_charge_the_counter_never_leaves_ends_at_the_cap(
    tmp_path: Path,
) -> None:
    text = (
        "recipe: r\ninitial_charge: 100000 Ah\nsteps:\n  - id: discharge\n"
        "    discharge: 10 mA\n    until:\n      - charge <= 0.1 Ah: next\n"
    )
    res = await dry_run(write(tmp_path, text), max_hours=1)
    assert not res.finished
    assert res.end_reason.startswith(
        "did not finish within 1 h (--max-hours): at test time 1:00:00 in step 'discharge'"
    )


async def test_a_100k_row_profile_repeated_1000_times_stops_at_the_cap(tmp_path: Path) -> None:
    rows = "\n".join(f"{k},{0.01 if k % 2 else -0.01}" for k in range(100_000))
    (tmp_path / "p.csv").write_text("time_s,current_a\n" + rows + "\n", encoding="utf-8")
    text = "recipe: r\nsteps:\n  - id: drive\n    profile: {file: p.csv, repeat: 1000}\n"
    res = await dry_run(write(tmp_path, text), max_hours=1)
    assert not res.finished
    assert res.end_reason == (
        "did not finish within 1 h (--max-hours): at test time 1:00:00 in step 'drive'"
        " (1 of 1) of cycle 1 of 1, after 1 step start"
    )


async def test_a_million_cycles_keep_their_first_and_last_halves(tmp_path: Path) -> None:
    res = await dry_run(write(tmp_path, MILLION_CYCLES), max_hours=1)
    assert not res.finished
    summary = res.summary
    cycles = [c["cycle"] for c in summary["cycles"]]
    last = cycles[-1]
    assert last > DRY_RUN_CYCLES_KEPT  # there was something to leave out
    half = DRY_RUN_CYCLES_KEPT // 2
    assert cycles == [*range(1, half + 1), *range(last - half + 1, last + 1)]
    assert summary["cycles_omitted"] == last - DRY_RUN_CYCLES_KEPT
    assert len(summary["timeline"]) == DRY_RUN_EVENTS_KEPT
    assert summary["timeline_omitted"] > 0
    assert summary["timeline_omitted_at"] == DRY_RUN_EVENTS_KEPT // 2
    assert len(res.step_sequence) == DRY_RUN_EVENTS_KEPT
    assert res.steps_omitted == last - DRY_RUN_EVENTS_KEPT
    assert res.end_reason.startswith(
        f"did not finish within 1 h (--max-hours): at test time 1:00:00 in step 'tick'"
        f" (1 of 1) of cycle {last} of 1000000, after {last} step starts"
    )
    text = report(res)
    assert f"\n  … {summary['timeline_omitted']} events omitted …\n" in text
    assert f"\n  … {summary['cycles_omitted']} cycles omitted …\n" in text
    assert text.count("\n  cycle ") == DRY_RUN_CYCLES_KEPT


def result_files(folder: Path) -> tuple[list[dict[str, str]], dict[str, Any]]:
    """The BDF rows and the summary a dry run wrote under ``folder``."""
    (bdf,) = folder.rglob("*.bdf.csv")
    with bdf.open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return rows, json.loads((bdf.parent / "summary.json").read_text(encoding="utf-8"))


def jsonl_files(folder: Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The timeline events and the cycle rows a dry run wrote under ``folder``."""
    (timeline,) = folder.rglob(f"*{TIMELINE_SUFFIX}")
    (cycles,) = folder.rglob(f"*{CYCLES_SUFFIX}")
    return list(read_jsonl(timeline)), list(read_jsonl(cycles))


async def test_result_files_get_every_row_while_memory_keeps_the_halves(tmp_path: Path) -> None:
    res = await dry_run(write(tmp_path, MILLION_CYCLES), max_hours=0.5, results_dir=tmp_path)
    rows, saved = result_files(tmp_path)
    assert len(rows) == res.summary["records"]
    assert int(rows[-1]["Cycle Count / 1"]) == res.summary["cycles"][-1]["cycle"]
    assert len(saved["timeline"]) <= DRY_RUN_EVENTS_KEPT
    assert len(saved["cycles"]) <= DRY_RUN_CYCLES_KEPT
    assert saved["end_reason"] == res.end_reason
    # ADR 0022: every event and every cycle in their files.
    events, rows = jsonl_files(tmp_path)
    assert len(events) == len(saved["timeline"]) + saved["timeline_omitted"]
    assert events[: DRY_RUN_EVENTS_KEPT // 2] == saved["timeline"][: DRY_RUN_EVENTS_KEPT // 2]
    assert events[-1] == saved["timeline"][-1]
    assert len(rows) == len(saved["cycles"]) + saved["cycles_omitted"]
    assert rows[-1] == saved["cycles"][-1]


# --- the bounded lists ----------------------------------------------------------------------
def test_first_and_last_keeps_the_first_and_the_latest_halves() -> None:
    kept: FirstAndLast[int] = FirstAndLast(4)
    dropped = [kept.append(k) for k in range(10)]
    assert list(kept) == [0, 1, 8, 9]
    assert len(kept) == 4 and kept.omitted == 6
    assert dropped == [None, None, None, None, 2, 3, 4, 5, 6, 7]


def test_first_and_last_under_its_limit_keeps_everything() -> None:
    kept: FirstAndLast[str] = FirstAndLast(5)
    for item in "abc":
        kept.append(item)
    assert list(kept) == ["a", "b", "c"] and kept.omitted == 0


def test_a_live_tests_collector_keeps_everything_in_its_files_and_its_summary_says_so() -> None:
    # A bench's test record is its files (every event, every cycle: ADR 0022); its
    # summary, like a dry run's, keeps the first and the latest and counts the others.
    collector = ResultCollector("ch0", "r", "t")
    assert (collector.events_kept, collector.cycles_kept) == (LIVE_EVENTS_KEPT, LIVE_CYCLES_KEPT)
    assert collector.summary("", "Running")["timeline_omitted"] == 0
    assert collector.summary("", "Running")["cycles_omitted"] == 0
    whole = ResultCollector("ch0", "r", "t", events_kept=None, cycles_kept=None)
    assert "timeline_omitted" not in whole.summary("", "Running")
    assert "cycles_omitted" not in whole.summary("", "Running")
