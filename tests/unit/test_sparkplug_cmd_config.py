"""The ``sparkplug.commands`` section: off by default; enabled needs the primary host's id;
a wrong one is refused with file:line:col; a bench's edge node gets the settings."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app import build_bench
from supervisor.cli.main import main
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.sparkplug import CommandSettings

ROOT = Path(__file__).resolve().parents[2]


def bench_text(tmp: Path, commands: str) -> str:
    data: dict[str, Any] = yaml.safe_load(
        (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    )
    data["devices"] = {"chadeche": data["devices"]["chadeche"]}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    for key in ("tags", "simulation", "safety", "influxdb"):
        data.pop(key, None)
    data["state_dir"] = str(tmp / "var")
    text = yaml.safe_dump(data, sort_keys=False)
    return text + "sparkplug:\n  broker: mqtt://127.0.0.1\n  group: Lab\n" + commands


def test_commands_are_off_by_default(tmp_path: Path) -> None:
    path = tmp_path / "bench.yaml"
    path.write_text(bench_text(tmp_path, ""), encoding="utf-8")
    bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
    assert bench.sparkplug is not None
    assert bench.sparkplug.settings.commands == CommandSettings(False, None)


def test_enabled_commands_and_the_primary_host_reach_the_edge_node(tmp_path: Path) -> None:
    path = tmp_path / "bench.yaml"
    text = "  commands:\n    enabled: true\n    primary_host: scada\n"
    path.write_text(bench_text(tmp_path, text), encoding="utf-8")
    bench = build_bench(load_bench(path), VirtualClock(), in_process=True)
    assert bench.sparkplug is not None
    assert bench.sparkplug.settings.commands == CommandSettings(True, "scada")


@pytest.mark.parametrize(
    ("commands", "key", "where", "message"),
    [
        (
            "  commands:\n    enabled: true\n",
            "enabled",  # the section's first line: where its error is told
            "sparkplug.commands:",
            "enabled: true needs primary_host",
        ),
        (
            "  commands:\n    primary_host: scada/1\n",
            "primary_host",
            "sparkplug.commands.primary_host:",
            "String should match pattern",
        ),
    ],
)
def test_a_wrong_section_is_refused_with_file_line_and_column(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    commands: str,
    key: str,
    where: str,
    message: str,
) -> None:
    path = tmp_path / "bench.yaml"
    text = bench_text(tmp_path, commands)
    path.write_text(text, encoding="utf-8")
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    lines = text.splitlines()
    line = next(i for i, x in enumerate(lines, 1) if x.startswith(f"    {key}:"))
    column = 5 if where == "sparkplug.commands:" else 5 + len(key) + 2  # the value's
    assert f"{path}:{line}:{column}: {where}" in err
    assert message in err
