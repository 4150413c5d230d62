"""The OPC UA server's settings (the I/O map's ``opcua:`` section), apart from the server:
the commands that only read them (``supervisor opcua add-user``, the process that starts
the server, ADR 0029) import no asyncua."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from supervisor.config.models import BenchConfig

__all__ = ["MIN_SAMPLING_S", "PATH", "Identification", "OpcUaSettings", "sampling_interval_s"]

PATH: Final = "supervisor"
"""The endpoint's path: ``opc.tcp://<host>:<port>/supervisor``."""


@dataclass(frozen=True, slots=True)
class Identification:
    """The bench's identification (the I/O map's ``identification:``, OPC 40001-1): what a
    client reads under Bench/Identification. Empty: not configured."""

    manufacturer: str = ""
    manufacturer_uri: str = ""
    model: str = ""
    serial_number: str = ""
    product_instance_uri: str = ""
    asset_id: str = ""
    location: str = ""
    year_of_construction: int | None = None


@dataclass(frozen=True, slots=True)
class OpcUaSettings:
    """The I/O map's ``opcua:`` section with its paths resolved."""

    bench: str
    description: str
    host: str
    port: int
    security: tuple[str, ...]
    anonymous: bool
    users_file: Path
    pki_dir: Path
    scan_period_s: float
    sampling_interval_s: float = 0.0
    """How often the scan hands changed tags to the server (``OpcUaFeed``); 0: every scan."""
    max_connections: int = 64
    """Open connections at most (``opcua.max_connections``): one more is closed at once."""
    activation_timeout_s: float = 10.0
    """A connection without an activated session this long is closed."""
    identification: Identification = Identification()
    """The bench's identification (serial number and product URI defaulted at build)."""

    @classmethod
    def of(cls, cfg: BenchConfig) -> OpcUaSettings:
        o = cfg.opcua
        base = Path(cfg.state_dir) / "opcua"
        return cls(
            bench=cfg.bench,
            description=cfg.description,
            host=o.host,
            port=o.port,
            security=o.security_modes,
            anonymous=o.anonymous,
            users_file=Path(o.users_file) if o.users_file else base / "users.yaml",
            pki_dir=Path(o.pki_dir) if o.pki_dir else base / "pki",
            scan_period_s=cfg.scan.period_s,
            sampling_interval_s=sampling_interval_s(cfg.scan.period_s, o.sampling_interval_s),
            max_connections=o.max_connections,
            activation_timeout_s=o.activation_timeout_s,
            identification=Identification(**cfg.identification.model_dump()),
        )

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}/{PATH}"


MIN_SAMPLING_S: Final = 0.05
"""The shortest default sampling interval: 20 values a second is what the fastest SCADA
trends ask; at a 10 ms scan, handing the server every scan's changes cost the scan's
process about a third of its CPU (issue 13's load case, py-spy) for values no client
samples that fast."""


def sampling_interval_s(scan_period_s: float, configured_s: float | None) -> float:
    """The interval the server samples the scan at: ``opcua.sampling_interval_s``, else the
    scan period but at least ``MIN_SAMPLING_S``; never shorter than the scan period (the
    tags do not change faster)."""
    wanted = configured_s if configured_s is not None else max(scan_period_s, MIN_SAMPLING_S)
    return max(wanted, scan_period_s)
