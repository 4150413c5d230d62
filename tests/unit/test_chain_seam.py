"""The chain's seam: it sees its channel through tags only, and layers do not cross."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from supervisor.chains.port import ChannelPort
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.tags import TagDB

ROOT = Path(__file__).resolve().parents[2] / "supervisor"


def imports_of(package: str) -> dict[str, set[str]]:
    """Every module each file of ``supervisor/<package>`` imports (absolute names)."""
    out: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names.add(node.module)
        out[str(path.relative_to(ROOT))] = names
    return out


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("chains", ("supervisor.channels", "supervisor.devices", "supervisor.publish")),
        ("publish", ("supervisor.chains", "supervisor.channels", "supervisor.devices")),
    ],
)
def test_a_layer_does_not_import_its_neighbours(package: str, forbidden: tuple[str, ...]) -> None:
    crossing = {
        f"{file} imports {name}"
        for file, names in imports_of(package).items()
        for name in names
        if name.startswith(forbidden)
    }
    assert not crossing


def test_the_chain_package_never_names_the_channel_class() -> None:
    for path in (ROOT / "chains").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        assert "Channel" not in names, path


@pytest.fixture
def channel() -> tuple[TagDB, Channel, ChannelPort]:
    db = TagDB()
    ch = Channel("ch0", db, ChannelLimits((-0.4, 0.4), (0.8, 1.9)), capacity_ah=2.0)
    return db, ch, ChannelPort.from_tags(db, "ch0", Mode.AUTO.value)


def test_the_port_reads_the_channels_own_tags(
    channel: tuple[TagDB, Channel, ChannelPort],
) -> None:
    db, ch, port = channel
    assert port.name == "ch0"
    assert port.voltage is ch.voltage and port.charge_ah is ch.charge_ah
    assert port.fault is ch.fault and port.current_cmd is ch.current_cmd
    db.update(ch.charged_ah, 0.5)
    db.update(ch.discharged_wh, 0.25)
    assert port.counters() == {
        "charged_ah": 0.5,
        "discharged_ah": 0.0,
        "charged_wh": 0.0,
        "discharged_wh": 0.25,
    }


def test_a_request_writes_the_auto_tags_the_channel_takes_its_setpoints_from(
    channel: tuple[TagDB, Channel, ChannelPort],
) -> None:
    db, ch, port = channel
    port.request(0.3, 1.6, True)
    assert (ch.auto_current.value, ch.auto_voltage.value, ch.auto_active.value) == (0.3, 1.6, True)
    assert db["ch0.auto_current"].value == 0.3


def test_taking_control_puts_the_channel_in_auto_and_drops_the_manual_enable(
    channel: tuple[TagDB, Channel, ChannelPort],
) -> None:
    db, ch, port = channel
    db.update(ch.enable, True)
    assert not port.in_auto
    port.take_control()
    assert ch.mode.value == "auto" and ch.enable.value is False
    assert port.in_auto


def test_the_port_reports_the_channels_latched_trip(
    channel: tuple[TagDB, Channel, ChannelPort],
) -> None:
    db, ch, port = channel
    assert port.fault_text() == ""
    db.update(ch.fault, "voltage input BAD (not_connected)")
    assert port.fault_text() == "voltage input BAD (not_connected)"


def test_a_port_of_a_channel_without_its_tags_names_the_missing_tag() -> None:
    with pytest.raises(KeyError, match=r"unknown tag 'ch9\.voltage'"):
        ChannelPort.from_tags(TagDB(), "ch9", "auto")
