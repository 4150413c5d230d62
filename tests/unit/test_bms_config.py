"""The BMS's I/O map entry: the keys an integrator sets for the bench's CAN link."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.cli.main import main
from supervisor.devices.bms.config import BmsDevice

ROOT = Path(__file__).resolve().parents[2]


def test_padded_frames_are_decoded_by_default_and_can_be_refused() -> None:
    assert BmsDevice.model_validate({"driver": "bms-can"}).allow_extra_bytes is True
    strict = BmsDevice.model_validate({"driver": "bms-can", "allow_extra_bytes": False})
    assert strict.allow_extra_bytes is False


def test_supervisor_check_accepts_allow_extra_bytes_in_an_io_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    assert "    driver: bms-can\n" in text
    path = tmp_path / "bms-strict.yaml"
    path.write_text(
        text.replace("driver: bms-can\n", "driver: bms-can\n    allow_extra_bytes: false\n"),
        encoding="utf-8",
    )
    assert main(["check", str(path)]) == 0, capsys.readouterr().err
