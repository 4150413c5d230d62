"""A direct poll of the Chadèche driver keeps a board's last GOOD reading in one test
(its memo, ``_Board.kept``; docs/adr/0018-scan-performance.md, "Dry run") exactly as
reading each point again would (``ChadecheDriver._read_points``): the same samples kept
(the very objects, which the scan's input copy only stamps) or made anew, with the same
values, qualities, reasons and times, whatever the writes, the cell, the faults, a
failing thermometer, a board at full scale and awaited polls do in between."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

from hypothesis import example, given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.errors import DeviceIOError
from supervisor.devices.chadeche import ChadecheDriver
from supervisor.devices.chadeche.protocol import Calibration
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus


class Cell:
    """A cell whose open-circuit voltage the test sets (plus an IR drop)."""

    def __init__(self) -> None:
        self.ocv_v = 1.25
        self.current_a = 0.0

    def step(self, current_a: float, dt_s: float) -> None:
        self.current_a = current_a

    def voltage_at(self, current_a: float) -> float:
        return self.ocv_v + 0.05 * current_a

    @property
    def terminal_voltage_v(self) -> float:
        return self.voltage_at(self.current_a)


class Rig:
    """A driver polled ``how``: "memo" (direct, as shipped), "points" (direct, every
    board read point by point) or "awaited" (the plain awaited path)."""

    def __init__(self, how: str, addresses: tuple[int, ...] = (0, 2, 3)) -> None:
        self.how = how
        self.clock = VirtualClock()
        self.cells = {0: Cell(), 2: Cell()}
        self.bus = SimChadecheBus(self.clock, {a: SimBoard(c) for a, c in self.cells.items()})
        self.probe_fails: type[Exception] | None = None
        cal = {
            0: Calibration(),
            2: Calibration(current_slope=1.02, current_offset_ma=-0.5, voltage_slope=0.99),
            3: Calibration(),  # no board answers: full scale, a failed sensor
        }
        cal = {a: cal[a] for a in addresses}
        self.driver = ChadecheDriver(
            "cd", self.clock, self.bus, cal, poll_period_s=1.0, temperature_probe=self.probe
        )

    def probe(self, address: int) -> float | None:
        if self.probe_fails is ValueError and address == 2:
            raise ValueError("a bug in the thermometer")  # after board 0's reading
        if self.probe_fails is DeviceIOError and address == 2:
            raise DeviceIOError("thermometer", "unplugged")  # a poll failing half-way
        return None if address == 3 else 20.0 + self.clock.now()

    async def apply(self, o: tuple[Any, ...]) -> None:
        kind, d = o[0], self.driver
        if kind in ("poll", "awaited poll"):
            if self.how == "points":
                for board in d._boards.values():
                    board.kept = None  # read point by point
            d._direct = kind == "poll" and self.how != "awaited"
            with contextlib.suppress(ValueError):  # no device failure: out of the poll
                await d.poll()
        elif kind == "write":
            d.write(f"b{o[1]}.current_set", o[2])
            await d.flush()
        elif kind == "ocv":
            self.cells[o[1]].ocv_v = o[2]  # 4.1 V and above: the ADC at full scale
        elif kind == "wait":
            self.clock.advance(o[1])
        elif kind == "bus fault":
            self.bus.fault = DeviceIOError("bus", "cable pulled") if o[1] else None
        else:
            self.probe_fails = {"no": None, "device": DeviceIOError, "bug": ValueError}[o[1]]


def seen(r: Rig, before: dict[str, Any] | None = None) -> Any:
    """The image (each sample's contents, and whether it is the very object it was
    before the op), the raw log and the counters."""
    image = r.driver.image()
    return (
        {
            k: (s.value, s.quality, s.reason, s.t, before is None or s is before[k])
            for k, s in image.items()
        },
        list(r.driver.raw_log),
        r.driver.polls,
        r.driver.failures,
        r.driver.connected,
        list(r.bus.history),
    )


op = st.one_of(
    st.tuples(st.just("poll")),
    st.tuples(st.just("poll")),
    st.tuples(st.just("awaited poll")),
    # 0.5 A is clamped to 0.4 A: the same DAC code as 0.4 A, another reason.
    st.tuples(
        st.just("write"), st.sampled_from([0, 2]), st.sampled_from([0.0, 0.1, -0.2, 0.4, 0.5])
    ),
    st.tuples(st.just("ocv"), st.sampled_from([0, 2]), st.sampled_from([1.2, 1.2004, 4.5])),
    st.tuples(st.just("wait"), st.sampled_from([0.0, 1.0])),
    st.tuples(st.just("bus fault"), st.booleans()),
    st.tuples(st.just("probe fails"), st.sampled_from(["no", "device", "bug"])),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(op, max_size=50))
# The clamp lifted at the same DAC code (0.5 A clamped to 0.4 A, then 0.4 A).
@example([("write", 0, 0.5), ("poll",), ("write", 0, 0.4), ("poll",)])
# A poll failing after board 0 was read from its memo: its samples keep their times.
@example([("poll",), ("wait", 1.0), ("probe fails", "device"), ("poll",)])
# The same with an error that is no device failure (out of the poll, image untouched).
@example([("write", 0, 0.1), ("probe fails", "bug"), ("poll",), ("probe fails", "no"), ("poll",)])
def test_a_kept_reading_is_the_one_reading_each_point_again_gives(
    ops: list[tuple[Any, ...]],
) -> None:
    async def run() -> None:
        memo, points, awaited = Rig("memo"), Rig("points"), Rig("awaited")
        for o in [("poll",), ("wait", 1.0), *ops, ("wait", 1.0), ("poll",), ("poll",)]:
            before = [dict(r.driver.image()) for r in (memo, points)]
            for r in (memo, points, awaited):
                await r.apply(o)
            assert seen(memo, before[0]) == seen(points, before[1]), o
            assert seen(memo) == seen(awaited), o

    asyncio.run(run())


def test_a_steady_board_is_read_from_its_memo_alone() -> None:
    r = Rig("memo", addresses=(0, 2))

    def read_points(*args: Any) -> Any:
        raise AssertionError("a point read again")

    async def run() -> None:
        await r.driver.poll()
        r.clock.advance(1.0)
        await r.driver.poll()
        assert all(board.kept is not None for board in r.driver._boards.values())
        r.driver._read_points = read_points  # type: ignore[method-assign]
        r.clock.advance(1.0)
        await r.driver.poll()
        assert r.driver.polls == 3
        assert {s.t for s in r.driver.image().values()} == {2.0}

    asyncio.run(run())
