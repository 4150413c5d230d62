"""The one seam between a step chain and its channel: tags to read, requests to write.

A chain reads the channel's measurement, counter, fault and mode tags and requests a
setpoint through ``chN.auto_current`` / ``chN.auto_voltage`` / ``chN.auto_active``; the
channel's own logic (run after the chain in the same scan) clamps, protects and drives
the source, so a chain can never override a trip (docs/design.md, one scan). The chain never
sees the channel object, a driver or a device: only these tags, through the TagDB.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from supervisor.tags import Tag, TagDB


@dataclass(frozen=True, slots=True)
class ChannelPort:
    """A channel's tags as a step chain sees them (built by the composition root)."""

    name: str
    db: TagDB
    auto_mode: str  # the value of ``chN.mode`` that hands the channel to its chain
    # Read.
    voltage: Tag
    current: Tag
    temperature: Tag
    power: Tag
    charge_ah: Tag
    energy_wh: Tag
    charged_ah: Tag
    discharged_ah: Tag
    charged_wh: Tag
    discharged_wh: Tag
    current_cmd: Tag
    fault: Tag
    fault_action: Tag  # "abort" when a trip aborts the test (the e-stop), else "hold"
    armed: Tag  # the power path is closed: the recipe's limits apply
    # Written (mode is also read).
    mode: Tag
    enable: Tag
    manual_current: Tag
    auto_current: Tag
    auto_voltage: Tag
    auto_active: Tag
    manual_mode: str = "manual"  # the value of ``chN.mode`` that gives it to the operator
    # Read into every result record after the BDF columns (the I/O map's ``record:``): the
    # BMS's cells, the other measurements of the pack. Empty: a record costs nothing more.
    record: tuple[Tag, ...] = ()

    @classmethod
    def from_tags(
        cls,
        db: TagDB,
        channel: str,
        auto_mode: str,
        manual_mode: str = "manual",
        record: tuple[str, ...] = (),
    ) -> ChannelPort:
        """The port of channel ``channel`` from its ``<channel>.<field>`` tags; ``record``:
        the tags its result records carry besides (by name)."""
        tags = {
            f.name: db[f"{channel}.{f.name}"]
            for f in fields(cls)
            if f.name not in ("name", "db", "auto_mode", "manual_mode", "record")
        }
        return cls(
            name=channel,
            db=db,
            auto_mode=auto_mode,
            manual_mode=manual_mode,
            record=tuple(db[n] for n in record),
            **tags,
        )

    @property
    def in_auto(self) -> bool:
        return self.mode.value == self.auto_mode

    def fault_text(self) -> str:
        """The channel's latched trip, "" when there is none."""
        return str(self.fault.value or "")

    @property
    def trip_aborts(self) -> bool:
        """The channel's trip aborts the test (an e-stop), rather than holding it."""
        return bool(self.fault.value) and self.fault_action.value == "abort"

    @property
    def limits_armed(self) -> bool:
        """Recipe limits apply: before the contactor closes the source's terminals do not
        see the battery, and a limit would trip on a reading of 0 V."""
        return self.armed.value is True

    def take_control(self) -> None:
        """Hand the channel to its chain at the start of a test: Auto mode, and the manual
        enable dropped so that a later switch to Manual does not re-energise by itself."""
        self.db.update(self.mode, self.auto_mode)
        self.db.update(self.enable, False)

    def release_control(self) -> None:
        """Give the channel back to the operator when its test is reset: Manual, enable
        off, setpoint 0 A (bumpless: nothing flows until the operator asks for it)."""
        db = self.db
        db.update(self.manual_current, 0.0)
        db.update(self.enable, False)
        db.update(self.mode, self.manual_mode)
        self.request(0.0, 0.0, False)

    @property
    def manual_driven(self) -> bool:
        """The operator drives the channel: Manual mode with enable on."""
        return not self.in_auto and self.enable.value is True

    def request(self, current_a: float, voltage_v: float, active: bool) -> None:
        """This scan's request: current (A, + charges), CV target (V, 0: none), and
        whether the power stage should be on."""
        db = self.db
        db.update(self.auto_current, current_a)
        db.update(self.auto_active, active)
        db.update(self.auto_voltage, voltage_v)

    def counters(self) -> dict[str, float]:
        """The counters whose test- and cycle-scoped differences go into the records (BDF:
        test-scoped counters never reset, cycle-scoped ones reset at a new cycle)."""
        return {
            "charged_ah": self.charged_ah.as_float(),
            "discharged_ah": self.discharged_ah.as_float(),
            "charged_wh": self.charged_wh.as_float(),
            "discharged_wh": self.discharged_wh.as_float(),
        }
