"""A Modbus TCP client that is not the project's code, nor pymodbus's: an MBAP header and a
PDU in a few lines of struct over a blocking socket (Modbus Application Protocol v1.1b3 and
Modbus Messaging on TCP/IP v1.0b), so that the server is tested against the protocol, not
against the library it is built on."""

from __future__ import annotations

import socket
import struct
from dataclasses import dataclass, field

TIMEOUT_S = 5.0


class ModbusException(Exception):
    """The server answered exception ``code`` (01 illegal function, 02 illegal data
    address, 03 illegal data value, 04 server device failure)."""

    def __init__(self, function: int, code: int) -> None:
        super().__init__(f"function {function:#04x}: exception {code:02d}")
        self.function = function
        self.code = code


@dataclass
class RawClient:
    host: str
    port: int
    unit: int = 1
    source: str | None = None  # the client's own address (another loopback one: 127.0.0.2)
    sock: socket.socket = field(init=False)
    _tid: int = 0

    def __post_init__(self) -> None:
        source = None if self.source is None else (self.source, 0)
        self.sock = socket.create_connection((self.host, self.port), TIMEOUT_S, source)
        self.sock.settimeout(TIMEOUT_S)

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> RawClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the frame ----------------------------------------------------------------------
    def send_raw(self, frame: bytes) -> None:
        self.sock.sendall(frame)

    def recv_frame(self) -> tuple[int, int, bytes]:
        """(transaction id, unit, PDU) of the next answer; ``ConnectionError`` when the
        server closed the connection."""
        head = self._recv(7)
        tid, proto, length, unit = struct.unpack(">HHHB", head)
        assert proto == 0
        return tid, unit, self._recv(length - 1)

    def _recv(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("closed by the server")
            out += chunk
        return out

    def request(self, function: int, data: bytes, unit: int | None = None) -> bytes:
        """The answer's data (after the function code); ``ModbusException`` for an
        exception answer."""
        self._tid = (self._tid + 1) & 0xFFFF
        pdu = bytes([function]) + data
        u = self.unit if unit is None else unit
        self.send_raw(struct.pack(">HHHB", self._tid, 0, len(pdu) + 1, u) + pdu)
        tid, _, answer = self.recv_frame()
        assert tid == self._tid, (tid, self._tid)
        if answer[0] == function | 0x80:
            raise ModbusException(function, answer[1])
        assert answer[0] == function, answer
        return answer[1:]

    # --- the functions --------------------------------------------------------------------
    def read_registers(self, address: int, count: int, *, holding: bool = False) -> list[int]:
        data = self.request(3 if holding else 4, struct.pack(">HH", address, count))
        assert data[0] == 2 * count
        return list(struct.unpack(f">{count}H", data[1:]))

    def read_bits(self, address: int, count: int, *, coils: bool = False) -> list[bool]:
        data = self.request(1 if coils else 2, struct.pack(">HH", address, count))
        packed = data[1:]
        return [bool(packed[i // 8] >> (i % 8) & 1) for i in range(count)]

    def write_register(self, address: int, value: int) -> None:
        data = self.request(6, struct.pack(">HH", address, value))
        assert data == struct.pack(">HH", address, value)

    def write_registers(self, address: int, values: list[int]) -> None:
        body = struct.pack(f">HHB{len(values)}H", address, len(values), 2 * len(values), *values)
        data = self.request(16, body)
        assert data == struct.pack(">HH", address, len(values))

    def write_coil(self, address: int, on: bool) -> None:
        data = self.request(5, struct.pack(">HH", address, 0xFF00 if on else 0))
        assert data == struct.pack(">HH", address, 0xFF00 if on else 0)


def float_of(words: list[int], word_order: str = "big") -> float:
    hi, lo = words if word_order == "big" else (words[1], words[0])
    value: float = struct.unpack(">f", struct.pack(">HH", hi, lo))[0]
    return value


def words_of(x: float, word_order: str = "big") -> list[int]:
    hi, lo = struct.unpack(">HH", struct.pack(">f", x))
    return [hi, lo] if word_order == "big" else [lo, hi]


def poll(
    host: str, port: int, ranges: list[tuple[int, int]], seconds: float, period_s: float
) -> dict[str, object]:
    """Read every (address, count) of ``ranges`` (input registers) each ``period_s`` for
    ``seconds``: a SCADA poller, bounded in count and time. Returns what it did."""
    import time

    polls, registers, errors = 0, 0, []
    with RawClient(host, port) as c:
        end = time.monotonic() + seconds
        next_t = time.monotonic()
        while time.monotonic() < end:
            for address, count in ranges:
                try:
                    registers += len(c.read_registers(address, count))
                except ModbusException as exc:
                    errors.append(str(exc))
            polls += 1
            next_t += period_s
            time.sleep(max(0.0, next_t - time.monotonic()))
    return {"polls": polls, "registers": registers, "errors": errors[:10]}


if __name__ == "__main__":  # the poller in a process of its own (tests/integration)
    import json
    import sys

    host, port, seconds, period, spec = sys.argv[1:6]
    wanted = [tuple(int(x) for x in r.split(":")) for r in spec.split(",")]
    print(json.dumps(poll(host, int(port), wanted, float(seconds), float(period))), flush=True)  # type: ignore[arg-type]
