"""The pipe to the OPC UA server's process (ADR 0029): what the bench accepts from it, and
tag values that cross it unchanged."""

from __future__ import annotations

import asyncio
import io
import os
import pickle

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.core.quality import Quality, Reason
from supervisor.publish.opcua.feed import Update
from supervisor.publish.opcua.ports import Answer, Request
from supervisor.publish.opcua.wire import (
    HEADER,
    MAX_FRAME_BYTES,
    SafeUnpickler,
    frame,
    read_frame,
    tag_row,
    update_of,
)


def bench_reads(data: bytes) -> object:
    async def read() -> object:
        reader = asyncio.StreamReader()
        reader.feed_data(data)
        reader.feed_eof()
        return await read_frame(reader, safe=True)

    return asyncio.run(read())


class Boom:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.system, ("echo pwned",))


def test_the_bench_accepts_requests_answers_and_plain_data_from_the_server() -> None:
    req = Request("channel", "ch0", "start", {"recipe": "d", "current_a": 0.3}, "opcua:alice")
    message = ("op", 7, req)
    assert bench_reads(frame(message)) == message
    assert bench_reads(frame(("status", 3, 1200))) == ("status", 3, 1200)
    assert bench_reads(frame(("answer", 1, Answer(True, "ok")))) == (
        "answer",
        1,
        Answer(True, "ok"),
    )


@pytest.mark.parametrize(
    "hostile",
    [Boom(), ("op", 1, Boom()), Quality.GOOD, io.BytesIO(b"x")],
    ids=["reduce-to-os.system", "nested", "an-enum", "a-class"],
)
def test_anything_else_from_the_server_is_refused_without_running_it(hostile: object) -> None:
    body = pickle.dumps(hostile)
    with pytest.raises(pickle.UnpicklingError, match="not expected from the OPC UA server"):
        SafeUnpickler(io.BytesIO(body)).load()


def test_a_frame_longer_than_the_limit_closes_the_pipe() -> None:
    with pytest.raises(EOFError, match="frame of"):
        bench_reads(HEADER.pack(MAX_FRAME_BYTES + 1) + b"x")


def test_a_pipe_closed_mid_frame_is_an_end_not_a_crash() -> None:
    data = frame(("status", 1, 2))
    with pytest.raises(EOFError):
        bench_reads(data[:-3])


values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=False),
    st.text(),
)


@given(
    index=st.integers(0, 10_000),
    name=st.text(min_size=1),
    value=values,
    quality=st.sampled_from(list(Quality)),
    reason=st.sampled_from(list(Reason)),
    source_t=st.floats(allow_nan=False),
    server_t=st.floats(allow_nan=False),
)
def test_every_quality_reason_and_value_crosses_the_pipe_unchanged(
    index: int,
    name: str,
    value: object,
    quality: Quality,
    reason: Reason,
    source_t: float,
    server_t: float,
) -> None:
    u = Update(index, name, value, quality, reason, source_t, server_t)  # type: ignore[arg-type]
    back = update_of(pickle.loads(pickle.dumps(tag_row(u))))
    assert back == u
    assert back.quality is quality and back.reason is reason
