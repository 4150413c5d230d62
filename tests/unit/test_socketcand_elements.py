"""socketcand's ASCII elements cut out of a TCP stream, whatever its segments."""

from __future__ import annotations

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.fieldbus.socketcand import (
    ElementSplitter,
    parse_error_frame,
    parse_frame,
    send_element,
)

WORD = st.text(alphabet="0123456789ABCDEFabcdefhiknoprstw.", min_size=1, max_size=16)
ELEMENT = st.lists(WORD, min_size=1, max_size=4).map(" ".join)


@given(
    elements=st.lists(ELEMENT, max_size=12),
    gaps=st.lists(st.sampled_from(["", " ", "\n", " \n"]), min_size=12, max_size=12),
    cuts=st.lists(st.integers(0, 400), max_size=20),
)
def test_any_cut_of_the_stream_gives_the_same_elements(
    elements: list[str], gaps: list[str], cuts: list[int]
) -> None:
    stream = "".join(f"< {e} >{gap}" for e, gap in zip(elements, gaps, strict=False)).encode()
    splitter = ElementSplitter()
    got: list[str] = []
    last = 0
    for cut in sorted({c for c in cuts if c < len(stream)}):
        got += splitter.feed(stream[last:cut])
        last = cut
    got += splitter.feed(stream[last:])
    assert got == elements
    assert splitter.garbage_bytes == 0  # whitespace between elements is no garbage


def test_text_outside_elements_is_counted_and_skipped() -> None:
    splitter = ElementSplitter()
    assert splitter.feed(b"junk< ok >more< frame 1") == ["ok"]
    assert splitter.feed(b"23 <") == []  # a new '<' before the '>': the first was cut short
    assert splitter.feed(b" hi >") == ["hi"]
    assert splitter.garbage_bytes == len("junk") + len("more") + len("< frame 123")


def test_an_element_without_its_end_is_dropped_past_the_limit() -> None:
    splitter = ElementSplitter(max_element_bytes=16)
    assert splitter.feed(b"< " + b"A" * 40) == []
    assert splitter.feed(b" >< ok >") == ["ok"]
    assert splitter.garbage_bytes > 0


def test_a_frame_element_as_the_daemon_prints_it() -> None:
    msg = parse_frame("frame 2B0 1733412345.000250 C0A0000000000000")
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data), msg.dlc) == (
        0x2B0,
        False,
        bytes.fromhex("C0A0000000000000"),
        8,
    )
    assert msg.timestamp == pytest.approx(1733412345.00025)
    ext = parse_frame("frame 1ABCDEF0 1.000000 ")
    assert (ext.arbitration_id, ext.is_extended_id, bytes(ext.data)) == (0x1ABCDEF0, True, b"")


@pytest.mark.parametrize(
    "element",
    [
        "frame 2B0 x C0",  # time
        "frame 2B 1.0 C0",  # id of 2 digits
        "frame 800 1.0 C0",  # beyond 11 bits
        "frame 2B0 1.0 C",  # odd hex
        "frame 2B0 1.0 000000000000000000",  # 9 bytes
        "ok",
    ],
)
def test_a_malformed_frame_element_is_a_value_error(element: str) -> None:
    with pytest.raises(ValueError):
        parse_frame(element)


def test_an_error_element_is_an_error_frame() -> None:
    msg = parse_error_frame("error 004 1733412345.000001")
    assert msg.is_error_frame
    assert msg.arbitration_id == 0x004


def test_a_send_element_is_what_the_daemons_sscanf_reads() -> None:
    std = can.Message(arbitration_id=0x2B0, data=bytes.fromhex("42C80000"), is_extended_id=False)
    assert send_element(std) == "< send 2B0 4 42 C8 00 00 >"
    ext = can.Message(arbitration_id=0x1ABCDEF0, data=b"", is_extended_id=True)
    assert send_element(ext) == "< send 1ABCDEF0 0 >"
    with pytest.raises(ValueError):
        send_element(can.Message(arbitration_id=1, is_remote_frame=True, is_extended_id=False))
