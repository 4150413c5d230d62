"""The ``sparkplug:`` section of the I/O map: the least a user writes is a broker and a group;
the edge node id defaults to the bench name; a wrong broker URL or id is refused with
file:line:col; a bench with the section has the edge node among its scan publishers, its
channels and devices as Sparkplug devices, and a dry run leaves it out."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app import build_bench
from supervisor.app.dryrun import MAP_SERVICES
from supervisor.cli.main import main
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import bench_from_data, load_bench
from supervisor.publish.sparkplug import SparkplugPublisher

ROOT = Path(__file__).resolve().parents[2]


def sim_data(tmp: Path, sparkplug: dict[str, Any] | None) -> dict[str, Any]:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["devices"] = {"chadeche": data["devices"]["chadeche"]}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    for key in ("tags", "simulation", "safety", "influxdb"):
        data.pop(key, None)
    data["state_dir"] = str(tmp / "var")
    if sparkplug is not None:
        data["sparkplug"] = sparkplug
    return data


def write(tmp: Path, data: dict[str, Any]) -> Path:
    path = tmp / "bench.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def test_a_broker_and_a_group_are_enough_the_edge_node_is_the_bench(tmp_path: Path) -> None:
    cfg = load_bench(
        write(tmp_path, sim_data(tmp_path, {"broker": "mqtt://10.0.0.5", "group": "Lab"}))
    )
    sp = cfg.sparkplug
    assert sp is not None
    assert (sp.host, sp.port, sp.group, sp.edge_node, sp.keepalive_s) == (
        "10.0.0.5",
        1883,
        "Lab",
        None,
        30,
    )
    bench = build_bench(cfg, VirtualClock(), in_process=True)
    pub = bench.sparkplug
    assert isinstance(pub, SparkplugPublisher) and pub in bench.engine.publishers
    assert pub.settings.edge_node == "sim" == cfg.bench
    assert pub.session.layout.place("ch0.voltage") == ("ch0", "voltage")
    assert pub.session.layout.place("chadeche.connected") == ("chadeche", "connected")
    assert pub.session.layout.place("scan.count") == (None, "scan.count")
    assert "sparkplug.connected" in bench.db


def test_an_edge_node_id_and_keepalive_of_ones_own(tmp_path: Path) -> None:
    section = {"broker": "mqtt://broker:1884", "group": "Lab", "edge_node": "polytech-2"}
    cfg = load_bench(write(tmp_path, sim_data(tmp_path, {**section, "keepalive_s": 10})))
    bench = build_bench(cfg, VirtualClock(), in_process=True)
    assert bench.sparkplug is not None
    s = bench.sparkplug.settings
    assert (s.host, s.port, s.edge_node, s.keepalive_s) == ("broker", 1884, "polytech-2", 10)


def test_without_the_section_there_is_no_edge_node(tmp_path: Path) -> None:
    bench = build_bench(bench_from_data(sim_data(tmp_path, None)), VirtualClock(), in_process=True)
    assert bench.sparkplug is None and "sparkplug.connected" not in bench.db
    assert "sparkplug" in MAP_SERVICES  # a dry run publishes nothing


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("broker", "http://10.0.0.5:1883", "expected mqtt://host:port"),
        ("broker", "mqtt://10.0.0.5:99999", "the port must be a number from 1 to 65535"),
        ("broker", "mqtt://10.0.0.5:1883/x", "nothing after the port"),
        ("group", "Lab/A", "String should match pattern"),
        ("group", "Lab+", "String should match pattern"),
        ("edge_node", "bench #7", "String should match pattern"),
    ],
)
def test_a_wrong_broker_or_id_is_refused_with_file_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, value: str, message: str
) -> None:
    data = sim_data(tmp_path, None)
    text = yaml.safe_dump(data, sort_keys=False)
    section = {"broker": "mqtt://127.0.0.1:1883", "group": "Lab", key: value}
    text += "sparkplug:\n" + "".join(
        f"  {k}: {yaml.safe_dump(v).split(chr(10))[0]}\n" for k, v in section.items()
    )
    path = tmp_path / "bench.yaml"
    path.write_text(text, encoding="utf-8")
    lines = text.splitlines()
    line = next(i for i, x in enumerate(lines, 1) if x.startswith(f"  {key}:"))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}:{line}:{len(key) + 5}: sparkplug.{key}:" in err
    assert message in err


def test_its_tags_are_a_namespace_the_supervisor_generates(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["state_dir"] = str(tmp_path / "var")
    data["tags"].append({"name": "sparkplug.mine", "device": "adam", "point": "slot1.tc1"})
    assert main(["check", str(write(tmp_path, data))]) == 2
    assert "namespace the supervisor generates" in capsys.readouterr().err
