"""``supervisor bench pi-budget`` (issue 30): the four-Chadèche bench's share of a
Raspberry Pi 4 core, from instructions counted by valgrind.

The arithmetic and the reading of callgrind's output are specified here on fixtures; the
last test runs the whole budget for a window of seconds (valgrind needed: ``make
valgrind`` installs it, and ``make test`` does that first)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from supervisor.bench import pibudget, report
from supervisor.bench.pibudget import (
    NBODY,
    PI_BENCH,
    PUBLISHED,
    Bracket,
    Window,
    budget,
    budget_map,
    callgrind_total,
    per_unit,
    pi4_rate,
    pi4_share,
    window_scans,
)
from supervisor.cli.main import build_parser
from supervisor.devices.chadeche.config import ChadecheDevice
from supervisor.devices.registry import load_bench

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "pibudget"


@pytest.fixture
def at_root(monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(ROOT)
    return ROOT


# --- callgrind's output ---------------------------------------------------------------------
def test_a_dump_s_instructions_are_its_totals_line_not_a_sum_of_its_cost_lines() -> None:
    text = (DATA / "callgrind.out.1").read_text(encoding="utf-8")
    assert callgrind_total(text) == 1_215_198_418


def test_a_dump_with_only_a_summary_line_is_read_from_it() -> None:
    assert callgrind_total("events: Ir\nsummary: 42\n\nfn=(1) main\n0 42\n") == 42


def test_the_totals_line_wins_over_the_summary_line() -> None:
    assert callgrind_total("summary: 7\nfn=(1) f\n0 9\ntotals: 9\n") == 9


def test_output_without_a_total_is_an_error_not_zero() -> None:
    with pytest.raises(ValueError, match="totals"):
        callgrind_total("events: Ir\nfn=(1) main\n0 42\n")


# --- the arithmetic -------------------------------------------------------------------------
@given(
    start_up=st.integers(0, 10**11),
    each=st.integers(1, 10**9),
    units=st.integers(1, 10**6),
)
def test_two_runs_difference_cancels_what_both_do_once(
    start_up: int, each: int, units: int
) -> None:
    small = start_up + each * units
    big = start_up + each * 2 * units
    assert per_unit(small, big, units, 2 * units) == each


def test_the_bigger_run_must_do_more_work() -> None:
    with pytest.raises(ValueError):
        per_unit(10, 20, 5, 5)


def test_a_pi_4_core_runs_a_published_run_s_work_in_its_published_seconds() -> None:
    # 35,573,709 instructions a round here; 10,000 rounds took 79.216 s on the Pi 4.
    rate = pi4_rate(35_573_709, PI_BENCH)
    assert rate == pytest.approx(35_573_709 * 10_000 / 79.216)
    assert rate == pytest.approx(4.4907e9, rel=1e-4)
    # 51,074 a step here; 5,000,000 steps took 158.263 s.
    assert pi4_rate(51_074, NBODY) == pytest.approx(1.61358e9, rel=1e-4)


def test_the_share_is_the_bench_s_instructions_a_second_over_the_pi_4_s() -> None:
    assert pi4_share(60_912_201, 1.61358e9) == pytest.approx(0.03775, rel=1e-3)
    with pytest.raises(ValueError):
        pi4_share(1.0, 0.0)


def test_the_window_s_scans_are_the_midpoints_of_the_bracketed_counter() -> None:
    # Read 100 before switching the counter on and 104 after; 300 and 302 around the dump.
    scans, error = window_scans(Bracket(100, 104), Bracket(300, 302))
    assert scans == 199  # 301 - 102
    assert error == 3  # 2 + 1


def test_the_budget_uses_the_lower_pi_4_rate_so_the_higher_share() -> None:
    w = Window(
        instructions=1_215_198_418,
        scans=199.5,
        scans_error=3,
        wall_s=22,
        overruns=2,
        chains_running=4,
        channels=4,
    )
    b = budget(w, 0.1, {PI_BENCH.name: 35_573_709, NBODY.name: 51_074})
    assert b.per_scan == pytest.approx(1_215_198_418 / 199.5)
    assert b.per_s == pytest.approx(b.per_scan * 10)  # at a 100 ms scan
    assert b.rate == min(b.rates.values()) == b.rates[NBODY.name]
    assert b.share == pytest.approx(b.per_s / b.rates[NBODY.name])
    assert b.share > b.per_s / b.rates[PI_BENCH.name]


def test_a_window_without_scans_has_no_budget() -> None:
    w = Window(1, 0, 0, 1, 0, 0, 4)
    with pytest.raises(ValueError):
        budget(w, 0.1, {r.name: 1.0 for r in PUBLISHED})


# --- the workloads and the bench ------------------------------------------------------------
def _run(source: str, units: int) -> object:
    space: dict[str, object] = {}
    exec(source, space)  # the module's own constant sources
    return space["run"](units)  # type: ignore[operator]


def test_the_reference_loop_adds_the_first_n_integers() -> None:
    assert _run(pibudget.REFERENCE_LOOP_SRC, 10) == 45


def test_the_published_workloads_run_as_written() -> None:
    assert _run(PI_BENCH.source, 1) is None
    # Jupiter moves: its x after 10 steps is not where it started.
    assert _run(NBODY.source, 10) != pytest.approx(4.84143144246472090)


def test_the_budget_s_bench_is_the_pi_s_map_with_seed_000_s_four_simulated_boards(
    at_root: Path, tmp_path: Path
) -> None:
    data = budget_map()
    path = tmp_path / "pi-budget.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    cfg = load_bench(path)
    pi = load_bench(pibudget.PI_MAP)
    assert cfg.scan.period_s == pi.scan.period_s == 0.1
    assert [c.name for c in cfg.channels] == ["ch0", "ch1", "ch2", "ch3"]
    assert {c.source.board for c in cfg.channels} == {0, 1, 2, 3}
    chadeche = cfg.devices["chadeche"]
    assert isinstance(chadeche, ChadecheDevice)
    assert chadeche.backend == "sim"
    assert len(chadeche.boards) == 4
    assert chadeche.poll_period_s == pi.devices["chadeche"].poll_period_s
    # Stale later than on the Pi: valgrind holds the loop for seconds (not for the count).
    assert chadeche.stale_after_s == pibudget.STALE_UNDER_VALGRIND_S
    assert cfg.history.enabled is True
    assert cfg.opcua.enabled is True
    assert cfg.scan.realtime_priority is None


def test_the_command_line_knows_the_pi_budget() -> None:
    args = build_parser().parse_args(["bench", "pi-budget", "--seconds", "5"])
    assert args.what == "pi-budget"
    assert args.seconds == 5


# --- end to end (valgrind, a real supervisor run) -------------------------------------------
@pytest.mark.integration
def test_the_pi_budget_counts_a_window_of_the_running_bench_and_records_its_share(
    at_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if shutil.which("valgrind") is None:
        pytest.fail("valgrind is missing: `make valgrind` installs Debian's valgrind")
    results = tmp_path / "results.jsonl"
    monkeypatch.setenv(report.ENV, str(results))
    assert pibudget.pi_budget_benchmark(window_s=2.0, warmup_s=1.0, count_scale=0.05) == 0
    (figure,) = report.read(results)
    assert figure.unit == "%"
    assert 0 < figure.measured < 100
    assert "instructions/scan" in figure.reference
    assert "reference loop" in figure.reference


# --- counting the workloads in one process --------------------------------------------------
def test_the_segments_script_runs_each_workload_once_and_twice_between_cuts() -> None:
    script = pibudget.segments_script([(pibudget.REFERENCE_LOOP_SRC, 3), (NBODY.source, 2)])
    assert script.count("time.sleep(0)") == 1 + 2 * 2  # the start-up, then a cut a run
    exec(script, {})  # runs as it will under valgrind


def test_each_workload_s_unit_is_its_long_run_less_its_short_run() -> None:
    # Dumps: the start-up, then the loop's run of 1000 and 2000, then the N-body's 10 and 20.
    segments = [90_000_000, 600_000, 1_090_000, 700_000, 1_200_000]
    per = pibudget.per_unit_of_segments(segments, [("loop", 1000), ("nbody", 10)])
    assert per == [490.0, 50_000.0]


def test_a_missing_dump_is_an_error_not_a_shifted_count() -> None:
    with pytest.raises(ValueError, match="dumps"):
        pibudget.per_unit_of_segments([1, 2, 3, 4], [("loop", 1000), ("nbody", 10)])


def test_the_processes_counted_are_the_supervisor_s_children_by_their_parent_id(
    tmp_path: Path,
) -> None:
    # /proc/<pid>/stat: "pid (name) state ppid ..."; a name may hold spaces and parentheses.
    stats = {
        100: "100 (python) S 1 100",
        201: "201 (python -m supervisor.publish.opcua.child) S 100 100",
        202: "202 (a (b) c) R 100 100",
        300: "300 (valgrind) S 201 100",  # a grandchild: not the supervisor's own
    }
    for pid, text in stats.items():
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / "stat").write_text(text + " 0 0 0\n", encoding="utf-8")
    (tmp_path / "self").mkdir()
    assert pibudget.children_of(100, proc=tmp_path) == [201, 202]
    assert pibudget.children_of(999, proc=tmp_path) == []
