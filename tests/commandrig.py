"""A bench for command-path tests: sim.yaml's four Chadèche channels and its ADAM (e-stop
sense, a room thermocouple with an alarm limit), every device in process, virtual clock."""

from __future__ import annotations

from pathlib import Path

import yaml

from supervisor.app import Bench, build_bench
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.testing import run_scans

ROOT = Path(__file__).resolve().parents[1]

DISCHARGE = (
    "recipe: d\nsteps:\n  - {id: d, discharge: 200 mA, duration: 1 h}\n  - {id: r, rest: 1 h}\n"
)
SUPERVISED = (
    "recipe: s\nsteps:\n  - id: c\n    charge: 100 mA\n    until: [{voltage >= 5 V: next}]\n"
    "    supervision: {max_time: 10 s}\n"
)
CV_ON_CHADECHE = (
    "recipe: cv\nsteps:\n  - {id: c, cccv: {current: 100 mA, voltage: 1.5 V}, duration: 1 h}\n"
)


def io_map(tmp: Path) -> Path:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    data["devices"] = {k: data["devices"][k] for k in ("chadeche", "adam")}
    data["tags"] = [t for t in data["tags"] if t["device"] == "adam"]
    for t in data["tags"]:
        if t["name"] == "room.temp":
            t["alarms"] = {"h": 20.0}  # the simulated room is at 25 degC: a plain alarm
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    data["safety"] = {"estop": {"tag": "estop.ok"}}
    data["state_dir"] = str(tmp / "state")
    # The tests' recipes are written in their temporary folder (``recipe``).
    data["recipes"] = {"folders": [str(tmp)]}
    path = tmp / "bench.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def chadeche_map(tmp: Path) -> str:
    """sim.yaml's Chadèche stack alone (nothing to serve on the network)."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["hmi"]["login"] = False  # its HTTP clients do not log in
    data["devices"] = {"chadeche": data["devices"]["chadeche"]}
    data["channels"] = [c for c in data["channels"] if c["source"]["device"] == "chadeche"]
    data.pop("tags", None)
    data.pop("simulation", None)
    data.pop("safety", None)  # the seed-002 e-stop and its tags are not in this bench
    data.pop("opcua", None)  # `supervisor run` on it must not take 4840
    data.pop("modbus_server", None)  # nor Modbus (1502 may be taken)
    data["state_dir"] = str(tmp / "state")
    data["recipes"] = {"folders": [str(tmp)]}
    path = tmp / "chadeche.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return str(path)


def recipe(tmp: Path, text: str = DISCHARGE, name: str = "r.yaml") -> str:
    path = tmp / name
    path.write_text(text, encoding="utf-8")
    return str(path)


async def started_bench(tmp: Path) -> Bench:
    """The bench, its in-process simulators started and the first images in."""
    bench = build_bench(load_bench(io_map(tmp)), VirtualClock(), in_process=True)
    await bench.start()
    await run_scans(bench.engine, 10)
    return bench
