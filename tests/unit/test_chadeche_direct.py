"""The Chadèche driver's direct path on an in-process bus (docs/adr/0018-scan-performance.md,
"Dry run") gives exactly what the awaited path gives: the same images (values, qualities,
reasons, times), the same transfers on the bus, the same raw-log lines, the same counters,
whatever the writes, the cell, bus faults, a board at full scale and the clock do between
polls. The simulated board's caches (the ADC reply, the current it drives) answer what
computing them again would."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.errors import DeviceIOError
from supervisor.devices.chadeche import ChadecheDriver
from supervisor.devices.chadeche.protocol import (
    Calibration,
    Chip,
    DacChannel,
    dac_transfer,
    encode_adc_reply,
    encode_latch,
)
from supervisor.devices.chadeche.sim import SimBoard, SimChadecheBus


class Cell:
    """A deterministic cell whose voltage the test sets (plus an IR drop)."""

    def __init__(self) -> None:
        self.ocv_v = 1.25
        self.current_a = 0.0

    def step(self, current_a: float, dt_s: float) -> None:
        self.current_a = current_a
        self.ocv_v += current_a * dt_s * 1e-4

    def voltage_at(self, current_a: float) -> float:
        return self.ocv_v + 0.05 * current_a

    @property
    def terminal_voltage_v(self) -> float:
        return self.voltage_at(self.current_a)


@dataclass
class Rig:
    clock: VirtualClock
    bus: SimChadecheBus
    driver: ChadecheDriver
    cells: dict[int, Cell]


def rig(direct: bool) -> Rig:
    clock = VirtualClock()
    cells = {0: Cell(), 2: Cell()}
    bus = SimChadecheBus(clock, {a: SimBoard(c) for a, c in cells.items()})
    cal = {
        0: Calibration(),
        2: Calibration(current_slope=1.02, current_offset_ma=-0.5, voltage_slope=0.99),
        # No board answers at address 3: it reads full scale (sensor failure).
        3: Calibration(),
    }
    temps = {0: 24.5, 2: None, 3: None}
    driver = ChadecheDriver(
        "cd", clock, bus, cal, poll_period_s=1.0, temperature_probe=lambda a: temps[a]
    )
    driver._direct = direct
    return Rig(clock, bus, driver, cells)


def state(r: Rig) -> Any:
    d = r.driver
    image = {k: (s.value, s.quality, s.reason, s.t) for k, s in d.image().items()}
    return (
        image,
        list(d.raw_log),
        d.polls,
        d.failures,
        d.connected,
        d.last_error,
        list(r.bus.history),
        {a: (b.dac_a, b.dac_b, b.charging, b.transfers) for a, b in r.bus.boards.items()},
    )


op = st.one_of(
    st.tuples(st.just("poll")),
    st.tuples(st.just("flush")),
    st.tuples(st.just("current"), st.sampled_from([0, 2]), st.floats(-0.45, 0.45)),
    st.tuples(st.just("led"), st.sampled_from([0, 2]), st.floats(0.0, 1.0)),
    st.tuples(st.just("ocv"), st.sampled_from([0, 2]), st.floats(0.0, 4.5)),
    st.tuples(st.just("advance"), st.floats(0.0, 5.0)),
    st.tuples(st.just("fault"), st.booleans()),
)


async def apply(r: Rig, o: tuple[Any, ...]) -> None:
    kind = o[0]
    if kind == "poll":
        await r.driver.poll()
    elif kind == "flush":
        await r.driver.flush()
    elif kind == "current":
        r.driver.write(f"b{o[1]}.current_set", o[2])
    elif kind == "led":
        r.driver.write(f"b{o[1]}.led_duty", o[2])
    elif kind == "ocv":
        r.cells[o[1]].ocv_v = o[2]  # 4.1 V and above: the ADC at full scale
    elif kind == "advance":
        r.clock.advance(o[1])
    else:
        r.bus.fault = DeviceIOError("bus", "cable pulled") if o[1] else None


@settings(max_examples=150, deadline=None)
@given(st.lists(op, max_size=40))
def test_direct_polls_and_flushes_are_the_awaited_ones(ops: list[tuple[Any, ...]]) -> None:
    async def run() -> None:
        direct, awaited = rig(True), rig(False)
        for o in [("poll",), *ops, ("poll",)]:
            await apply(direct, o)
            await apply(awaited, o)
            assert state(direct) == state(awaited), o

    asyncio.run(run())


def test_the_direct_path_is_the_one_an_in_process_bus_gets() -> None:
    assert rig(True).driver._direct  # what rig(True) sets is the default: checked here
    clock = VirtualClock()
    bus = SimChadecheBus(clock, {0: SimBoard(Cell())})
    assert ChadecheDriver("cd", clock, bus, {0: Calibration()})._direct


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(st.just("ocv"), st.floats(-0.5, 4.5)),
            st.tuples(st.just("dac"), st.integers(0, 4095), st.booleans()),
            st.tuples(st.just("latch"), st.booleans()),
            st.tuples(st.just("gain"), st.floats(0.9, 1.1), st.floats(-2.0, 2.0)),
        ),
        max_size=40,
    )
)
def test_simulated_board_caches_answer_what_computing_again_would(
    ops: list[tuple[Any, ...]],
) -> None:
    cell = Cell()
    board = SimBoard(cell)
    for o in ops:
        if o[0] == "ocv":
            cell.ocv_v = o[1]
        elif o[0] == "dac":
            board.handle(Chip.DAC, dac_transfer(DacChannel.A if o[2] else DacChannel.B, o[1]))
        elif o[0] == "latch":
            board.handle(Chip.LATCH, encode_latch(o[1]))
        else:
            board.true_current_gain, board.true_current_offset_ma = o[1], o[2]
        assert board.current_a == board._current_now()
        assert board.handle(Chip.ADC, b"\x00\x00") == encode_adc_reply(board.adc_code())


def test_a_task_waiting_for_the_io_lock_goes_first_as_on_the_awaited_path() -> None:
    """A safe state waiting for the I/O lock when a poll comes: the poll waits behind it
    (asyncio.Lock serves its waiters first), on both paths alike."""

    async def run(r: Rig) -> Any:
        await r.driver.poll()
        r.driver.write("b0.current_set", 0.3)
        await r.driver.flush()
        await r.driver._io_cycle.acquire()
        safe = asyncio.create_task(r.driver.safe_state())
        await asyncio.sleep(0)  # it now waits for the lock
        r.driver._io_cycle.release()  # handed to it; it has not run yet
        await r.driver.poll()
        await safe
        return state(r)

    assert asyncio.run(run(rig(True))) == asyncio.run(run(rig(False)))
