"""The command-line tools around recipes: import, calibrate, dry-run, check."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import pytest

from supervisor.cli.main import main
from supervisor.devices.registry import load_bench

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "chadeche"


def test_import_chadeche_writes_a_recipe_that_check_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "fig10.yaml"
    code = main(
        [
            "import",
            "chadeche",
            str(DATA / "figure10-cp1252-crlf.txt"),
            "--prm",
            str(DATA / "chadeche0.prm"),
            "--option",
            "i=1300",
            "-o",
            str(out),
        ]
    )
    assert code == 0
    err = capsys.readouterr().err
    assert "current_slope:      0.9851" in err  # calibration goes to the I/O map, as a snippet
    assert main(["check", str(out)]) == 0


def test_import_refuses_to_overwrite_an_existing_file(tmp_path: Path) -> None:
    out = tmp_path / "x.yaml"
    out.write_text("keep me", encoding="utf-8")
    assert main(["import", "chadeche", str(DATA / "figure10.txt"), "-o", str(out)]) == 2
    assert out.read_text(encoding="utf-8") == "keep me"


def test_import_of_a_broken_sequence_file_exits_2_with_line_and_column(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["import", "chadeche", str(DATA / "bad-goto.txt")]) == 2
    err = capsys.readouterr().err
    assert f"{DATA / 'bad-goto.txt'}:6:17:" in err and "Traceback" not in err


def test_calibrate_current_from_typed_readings_writes_the_io_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    io_map = tmp_path / "sim.yaml"
    shutil.copy(ROOT / "io_maps" / "sim.yaml", io_map)
    # The staircase 0, 50 … 250 mA; the ammeter reads 2 % low, one reading mistyped.
    typed = "0\n49\nforty\n98\n147\n196\n245\n"
    monkeypatch.setattr("sys.stdin", io.StringIO(typed))
    code = main(
        [
            "calibrate",
            "current",
            "--recipe",
            str(ROOT / "recipes" / "current-calibration.yaml"),
            "--io-map",
            str(io_map),
            "--board",
            "2",
        ]
    )
    assert code == 0
    assert "is not a number" in capsys.readouterr().err
    board = next(b for b in load_bench(io_map).devices["chadeche"].boards if b.address == 2)  # type: ignore[union-attr]
    assert board.calibration.current_slope == pytest.approx(1 / 0.98)
    assert board.calibration.current_offset_ma == pytest.approx(0.0, abs=1e-9)


def test_dry_run_prints_the_timeline_duration_and_capacity_per_cycle(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["dry-run", str(ROOT / "recipes" / "capacity-test.yaml")]) == 0
    out = capsys.readouterr().out
    assert "starting step 2 discharge" in out
    assert "predicted duration:" in out
    assert "cycle 1: charged 0.0 mAh" in out and "discharged" in out


def test_dry_run_reports_a_refused_recipe_with_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["dry-run", str(ROOT / "recipes" / "liion-cccv-cycle.yaml"), "--model", "nimh-aa"])
    assert code == 2
    assert "cannot run on channel ch0" in capsys.readouterr().err


def test_sim_refuses_a_bench_whose_only_simulation_is_an_in_process_spi_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A simulated Chadèche bus lives inside the supervisor's process: nothing to serve.
    path = tmp_path / "chadeche-only.yaml"
    path.write_text(
        "bench: boards\n"
        "devices:\n"
        "  chadeche: {driver: chadeche, boards: [{address: 0}]}\n"
        "channels:\n"
        "  - {name: ch0, source: {device: chadeche, board: 0}, capacity_ah: 2.0,\n"
        "     limits: {current_a: [-0.4, 0.4], voltage_v: [0.8, 1.9]}}\n",
        encoding="utf-8",
    )
    assert main(["sim", str(path), "--control-port", "0"]) == 2
    assert "nothing to serve" in capsys.readouterr().err
