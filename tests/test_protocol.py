"""Wire protocol: CRC, round trips, strict rejection of corrupt frames, streaming resync."""

from __future__ import annotations

import dataclasses
import itertools
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpa_gym.hardware.protocol import (
    CRC_SIZE,
    FAULT_OVERPRESSURE,
    FAULT_SENSOR,
    FAULT_VENTED,
    FAULT_WATCHDOG_VENT,
    HEADER_SIZE,
    MAX_FRAME_SIZE,
    SYNC,
    Command,
    FrameDecoder,
    Message,
    ProtocolError,
    Telemetry,
    Vent,
    crc16_ccitt_false,
    crc16_table_walk,
    decode_frame,
    encode,
    fault_names,
)

u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)
f32 = st.floats(width=32)  # every float32, NaN and ±inf included: exact on the wire
commands = st.builds(Command, seq=u32, device_time_us=u64, pe_Pa=f32, pf_Pa=f32)
vents = st.builds(Vent, seq=u32, device_time_us=u64)
telemetry = st.builds(
    Telemetry,
    seq=u32,
    device_time_us=u64,
    x_m=st.floats(),
    v_mps=f32,
    pe_Pa=f32,
    pf_Pa=f32,
    faults=st.integers(0, 0xFFFF),
)
messages = st.one_of(commands, vents, telemetry)
garbage = st.binary(max_size=64).filter(lambda b: SYNC not in b)


def same_value(a: object, b: object) -> bool:
    """Equal, or both NaN; zeros must also agree in sign."""
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) or math.isnan(b):
            return math.isnan(a) and math.isnan(b)
        return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)
    return a == b


def same_message(a: Message, b: Message) -> bool:
    return type(a) is type(b) and all(
        same_value(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
    )


# --------------------------------------------------------------------------------------------
# CRC


def test_crc_check_value() -> None:
    # the catalogue check value of CRC-16/CCITT-FALSE, for both implementations
    for crc in (crc16_ccitt_false, crc16_table_walk):
        assert crc(b"123456789") == 0x29B1
        assert crc(b"") == 0xFFFF


@given(st.binary(max_size=256), st.integers(0, 256))
def test_crc_matches_the_specified_table_walk_and_chains(data: bytes, cut: int) -> None:
    """The C implementation used on the wire equals the table walk of the specification."""
    assert crc16_ccitt_false(data) == crc16_table_walk(data)
    assert crc16_ccitt_false(data[cut:], crc16_ccitt_false(data[:cut])) == crc16_ccitt_false(data)
    assert crc16_table_walk(data[cut:], crc16_table_walk(data[:cut])) == crc16_table_walk(data)


# --------------------------------------------------------------------------------------------
# Encoding and round trips


def test_frame_layout_matches_the_docstring_table() -> None:
    frame = encode(Command(seq=7, device_time_us=123_456, pe_Pa=2.5e5, pf_Pa=-1.0))
    assert len(frame) == HEADER_SIZE + 8 + CRC_SIZE == 26
    sync, mtype, seq, t_us, length = struct.unpack_from("<2sBIQB", frame)
    assert (sync, mtype, seq, t_us, length) == (b"\xa5\x5a", 0x01, 7, 123_456, 8)
    assert struct.unpack_from("<ff", frame, 16) == (2.5e5, -1.0)
    assert struct.unpack_from("<H", frame, 24)[0] == crc16_ccitt_false(frame[2:24])
    assert len(encode(Vent(0, 0))) == 18
    assert len(encode(Telemetry(0, 0, 0.0, 0.0, 0.0, 0.0, 0))) == 44 == MAX_FRAME_SIZE


@given(messages)
def test_round_trip_is_exact(msg: Message) -> None:
    frame = encode(msg)
    assert same_message(decode_frame(frame), msg)
    decoder = FrameDecoder()
    [decoded] = decoder.feed(frame)
    assert same_message(decoded, msg)
    assert (decoder.corrupt, decoder.skipped_bytes, decoder.buffered_bytes) == (0, 0, 0)


@given(
    st.floats(-3.0e38, 3.0e38),
    st.floats(-3.0e38, 3.0e38) | st.sampled_from([math.nan, math.inf, -math.inf]),
)
def test_command_pressures_are_rounded_to_float32(pe: float, pf: float) -> None:
    decoded = decode_frame(encode(Command(1, 2, pe, pf)))
    assert same_value(decoded.pe_Pa, float(np.float32(pe)))
    assert same_value(decoded.pf_Pa, float(np.float32(pf)))


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_values_pass_through(value: float) -> None:
    msg = Telemetry(1, 2, x_m=value, v_mps=value, pe_Pa=value, pf_Pa=value, faults=0)
    assert same_message(decode_frame(encode(msg)), msg)


@pytest.mark.parametrize(
    ("factory", "field"),
    [
        (lambda: Command(-1, 0, 0.0, 0.0), "Command.seq=-1"),
        (lambda: Command(2**32, 0, 0.0, 0.0), "Command.seq=4294967296"),
        (lambda: Vent(0, 2**64), "Vent.device_time_us="),
        (lambda: Command(0, 0, 1e39, 0.0), "Command.pe_Pa=1e+39"),
        (lambda: Command(0, 0, 0.0, "1"), "Command.pf_Pa='1'"),
        (lambda: Telemetry(0, 0, 0.0, 0.0, 0.0, 0.0, 0x10000), "Telemetry.faults=65536"),
        (lambda: Telemetry(0, 0, 0.0, 0.0, 0.0, 0.0, 1.5), "Telemetry.faults=1.5"),
    ],
)
def test_out_of_range_fields_are_named(factory, field: str) -> None:
    with pytest.raises(ValueError, match=field.replace("+", r"\+")):
        factory()


def test_fault_names() -> None:
    assert fault_names(0) == ()
    assert fault_names(FAULT_WATCHDOG_VENT | FAULT_VENTED) == ("watchdog_vent", "vented")
    assert fault_names(FAULT_OVERPRESSURE | FAULT_SENSOR | 0x100) == (
        "overpressure",
        "sensor",
        "0x0100",
    )


# --------------------------------------------------------------------------------------------
# Strict decoding


COMMAND_FRAME = encode(Command(seq=0x01020304, device_time_us=987_654_321, pe_Pa=3.0e5, pf_Pa=1e4))


def test_every_single_byte_corruption_of_a_command_is_rejected() -> None:
    """All 26 × 255 single-byte substitutions: sync, type, length by their checks, the rest
    (seq, time, payload floats, CRC) by the CRC, which detects every burst up to 16 bits."""
    rejected = 0
    for i in range(len(COMMAND_FRAME)):
        for value in range(256):
            if value == COMMAND_FRAME[i]:
                continue
            corrupted = bytearray(COMMAND_FRAME)
            corrupted[i] = value
            with pytest.raises(ProtocolError):
                decode_frame(bytes(corrupted))
            rejected += 1
    assert rejected == 26 * 255


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"\x00" + COMMAND_FRAME[1:], "bad sync 00 5a, expected a5 5a"),
        (COMMAND_FRAME[:10], "truncated frame: 10 bytes"),
        (COMMAND_FRAME[:-1], "truncated frame: 25 bytes, a Command frame is 26"),
        (b"", "truncated"),
        (COMMAND_FRAME + b"\x00", "1 trailing bytes"),
        (COMMAND_FRAME[:2] + b"\x7f" + COMMAND_FRAME[3:], "unknown message type 0x7f"),
        (COMMAND_FRAME[:15] + b"\x09" + COMMAND_FRAME[16:], "length mismatch for type 0x01"),
        (COMMAND_FRAME[:2] + b"\x02" + COMMAND_FRAME[3:], r"0x02 \(Vent\): header says 8"),
        (COMMAND_FRAME[:-2] + b"\x00\x00", r"CRC mismatch .*carries 0x0000, computed 0x"),
    ],
)
def test_decode_frame_says_what_is_wrong(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_frame(data)


@settings(max_examples=300)
@given(st.one_of(st.binary(max_size=64), st.binary(max_size=48).map(lambda b: SYNC + b)))
def test_decode_frame_raises_only_protocol_error(data: bytes) -> None:
    try:
        msg = decode_frame(data)
    except ProtocolError:
        return  # the only exception allowed
    # what does decode is a whole, well-formed frame of a known type
    assert isinstance(msg, Command | Vent | Telemetry)
    assert len(encode(msg)) == len(data)


def test_protocol_error_is_a_value_error() -> None:
    assert issubclass(ProtocolError, ValueError)


# --------------------------------------------------------------------------------------------
# Streaming decoder


@settings(max_examples=300)
@given(st.binary(max_size=512), st.lists(st.integers(0, 512), max_size=8))
def test_feed_never_raises_and_accounts_for_every_byte(data: bytes, cuts: list[int]) -> None:
    decoder = FrameDecoder()
    frame_bytes = 0
    edges = [0, *sorted(cuts), len(data)]
    for lo, hi in itertools.pairwise(edges):
        frame_bytes += sum(len(encode(m)) for m in decoder.feed(data[lo:hi]))
    total = frame_bytes + decoder.skipped_bytes + decoder.dropped_bytes + decoder.buffered_bytes
    assert total == len(data)
    assert decoder.buffered_bytes < MAX_FRAME_SIZE


@given(
    st.lists(st.tuples(garbage, messages), max_size=12),
    garbage,
    st.lists(st.integers(1, 64), min_size=1, max_size=20),
)
def test_frames_between_garbage_are_all_recovered(
    pieces: list[tuple[bytes, Message]], tail: bytes, chunk_sizes: list[int]
) -> None:
    stream = b"".join(g + encode(m) for g, m in pieces) + tail
    decoder = FrameDecoder()
    decoded: list[Message] = []
    pos, k = 0, 0
    while pos < len(stream):  # feed in chunks of the drawn sizes, cycling
        size = chunk_sizes[k % len(chunk_sizes)]
        decoded += decoder.feed(stream[pos : pos + size])
        pos, k = pos + size, k + 1
    assert len(decoded) == len(pieces)
    assert all(same_message(d, m) for d, (_, m) in zip(decoded, pieces, strict=True))
    assert decoder.corrupt == 0
    n_garbage = sum(len(g) for g, _ in pieces) + len(tail)
    assert decoder.skipped_bytes + decoder.buffered_bytes == n_garbage


def test_split_feed_one_byte_at_a_time() -> None:
    msgs = [Command(1, 10, 1.0e5, 2.0e5), Vent(2, 20), Telemetry(3, 30, 0.8, -0.125, 1e5, 0.0, 9)]
    decoder = FrameDecoder()
    decoded = []
    for byte in b"".join(encode(m) for m in msgs):
        out = decoder.feed(bytes([byte]))
        assert len(out) <= 1
        decoded += out
    assert decoded == msgs
    assert (decoder.corrupt, decoder.skipped_bytes, decoder.buffered_bytes) == (0, 0, 0)


def test_corrupt_frame_is_counted_and_the_next_one_recovered() -> None:
    good = Telemetry(5, 50, 0.7, 0.25, 3e5, 1e5, 0)
    bad = bytearray(encode(Command(4, 40, 1.0, 2.0)))
    bad[20] ^= 0x01  # payload bit flip: caught by the CRC
    decoder = FrameDecoder()
    assert decoder.feed(bytes(bad) + encode(good)) == [good]
    assert decoder.corrupt == 1
    assert decoder.skipped_bytes == len(bad)


def test_false_sync_in_front_of_a_frame_is_resynced() -> None:
    """A false sync whose 'header' swallows the real frame's start: resync from the next byte."""
    good = Command(9, 90, 5.0, 6.0)
    decoder = FrameDecoder()
    assert decoder.feed(SYNC + b"\x01" + encode(good)) == [good]
    assert decoder.corrupt == 1
    assert decoder.skipped_bytes == 3


@pytest.mark.parametrize("prefix", [b"\xa5", b"\xa5\xa5", b"\x5a", b"junk\xa5"])
def test_stray_sync_halves_before_a_frame_are_skipped(prefix: bytes) -> None:
    good = Vent(3, 30)
    decoder = FrameDecoder()
    assert decoder.feed(prefix) == []
    assert decoder.feed(encode(good)) == [good]
    assert (decoder.corrupt, decoder.skipped_bytes) == (0, len(prefix))


def test_buffer_is_bounded_keeping_the_newest_bytes() -> None:
    first, last = Vent(1, 1), Vent(2, 2)
    decoder = FrameDecoder(max_buffer_bytes=64 * 1024)
    filler = b"\x00" * 100_000
    out = decoder.feed(encode(first) + filler + encode(last))
    assert out == [last]
    assert decoder.dropped_bytes == len(encode(first)) + len(filler) + 18 - 64 * 1024
    with pytest.raises(ValueError, match="max_buffer_bytes=10"):
        FrameDecoder(max_buffer_bytes=10)


def test_telemetry_carries_the_acknowledged_command_seq() -> None:
    msg = Telemetry(3, 30, 0.8, -0.125, 1e5, 0.0, 9, ack_seq=0xFFFFFFFF)
    assert decode_frame(encode(msg)) == msg
    with pytest.raises(ValueError, match=r"Telemetry\.ack_seq"):
        Telemetry(0, 0, 0.0, 0.0, 0.0, 0.0, 0, ack_seq=-1)
