"""Binary wire protocol between the PC and the rig's microcontroller.

The rig has two electro-pneumatic pressure regulators (extensor, flexor) and a hip encoder. The PC
sends pressure set-points (:class:`Command`) or a vent request (:class:`Vent`); the device answers
with :class:`Telemetry`. Every quantity on the wire is SI: gauge pressures in Pa, hip height in m,
hip velocity in m/s, timestamps in µs.

## Frame

All multi-byte fields are little-endian. A frame is ``18 + length`` bytes:

| offset | size | field          | type | content                                               |
|-------:|-----:|----------------|------|-------------------------------------------------------|
| 0      | 2    | sync           | —    | ``A5 5A``                                             |
| 2      | 1    | type           | u8   | ``0x01`` Command, ``0x02`` Vent, ``0x81`` Telemetry   |
| 3      | 4    | seq            | u32  | sender's message counter (wraps at 2³²)               |
| 7      | 8    | device_time_us | u64  | timestamp [µs]; the device's clock in Telemetry       |
| 15     | 1    | length         | u8   | payload size n; fixed per type (table below)          |
| 16     | n    | payload        | —    | per type, below                                       |
| 16 + n | 2    | crc            | u16  | CRC-16/CCITT-FALSE over bytes 2 … 15 + n              |

CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR
(check value: ``crc16_ccitt_false(b"123456789") == 0x29B1``). It covers type, seq,
device_time_us, length and payload, not the sync bytes.

## Payloads

| type | message   | direction   | n  | payload (extensor before flexor)                        |
|-----:|-----------|-------------|---:|---------------------------------------------------------|
| 0x01 | Command   | PC → device | 8  | pe_Pa f32, pf_Pa f32: gauge pressure set-points         |
| 0x02 | Vent      | PC → device | 0  | — (both MPAs to atmosphere)                             |
| 0x81 | Telemetry | device → PC | 26 | x_m f64, v_mps f32, pe_Pa f32, pf_Pa f32, faults u16,   |
|      |           |             |    | ack_seq u32 (seq of the last Command the device applied) |

``faults`` is a bit set: :data:`FAULT_WATCHDOG_VENT` (1), :data:`FAULT_OVERPRESSURE` (2),
:data:`FAULT_SENSOR` (4), :data:`FAULT_VENTED` (8).

Non-finite floats (NaN, ±inf) are legal on the wire: they encode, and the decoders return them
unchanged. Judging values (limits, finiteness) is the env's job, not the protocol's.

## Decoding

:func:`decode_frame` is strict: it takes exactly one frame and raises :class:`ProtocolError` naming
what is wrong. :class:`FrameDecoder` takes a byte stream in arbitrary chunks, skips garbage,
counts corrupt frames and resynchronises; it never raises on any input bytes.
"""

from __future__ import annotations

import binascii
import operator
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

__all__ = [
    "CRC_SIZE",
    "FAULT_OVERPRESSURE",
    "FAULT_SENSOR",
    "FAULT_VENTED",
    "FAULT_WATCHDOG_VENT",
    "HEADER_SIZE",
    "MAX_FRAME_SIZE",
    "MSG_COMMAND",
    "MSG_TELEMETRY",
    "MSG_VENT",
    "SYNC",
    "Command",
    "FrameDecoder",
    "Message",
    "ProtocolError",
    "Telemetry",
    "Vent",
    "crc16_ccitt_false",
    "decode_frame",
    "encode",
    "fault_names",
]

SYNC = b"\xa5\x5a"

MSG_COMMAND = 0x01
MSG_VENT = 0x02
MSG_TELEMETRY = 0x81

FAULT_WATCHDOG_VENT = 1  # the device vented because commands stopped arriving
FAULT_OVERPRESSURE = 2  # a measured pressure exceeded the device's limit
FAULT_SENSOR = 4  # a pressure or encoder reading is invalid
FAULT_VENTED = 8  # vented on request (a Vent message)

_FAULT_NAMES = {
    FAULT_WATCHDOG_VENT: "watchdog_vent",
    FAULT_OVERPRESSURE: "overpressure",
    FAULT_SENSOR: "sensor",
    FAULT_VENTED: "vented",
}

_HEADER = struct.Struct("<2sBIQB")  # sync, type, seq, device_time_us, length
_CRC = struct.Struct("<H")
_COMMAND = struct.Struct("<ff")  # pe_Pa, pf_Pa
_TELEMETRY = struct.Struct("<dfffHI")  # x_m, v_mps, pe_Pa, pf_Pa, faults, ack_seq
_F32 = struct.Struct("<f")
_F64 = struct.Struct("<d")

HEADER_SIZE = _HEADER.size  # 16 bytes: sync .. length
CRC_SIZE = _CRC.size  # 2 bytes
MAX_FRAME_SIZE = HEADER_SIZE + _TELEMETRY.size + CRC_SIZE  # 44 bytes, the largest message

_U16_MAX = 0xFFFF
_U32_MAX = 0xFFFF_FFFF
_U64_MAX = 0xFFFF_FFFF_FFFF_FFFF


class ProtocolError(ValueError):
    """A frame that does not follow the wire format; the message says what is wrong."""


# --------------------------------------------------------------------------------------------
# CRC-16/CCITT-FALSE


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16_table_walk(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE by the table walk a device implements (the specification)."""
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data``: poly 0x1021, init 0xFFFF, MSB first, no final XOR.

    ``crc`` continues a running checksum (pass the previous result to checksum in pieces).
    Computed by ``binascii.crc_hqx`` (the same CRC in C; ``crc16_table_walk`` is the same in
    Python, ~30× slower), since every frame of a 500 Hz loop is checksummed twice.
    """
    return binascii.crc_hqx(data, crc)


# --------------------------------------------------------------------------------------------
# Messages


def _check_uint(owner: str, name: str, value: object, high: int) -> None:
    try:
        x = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ValueError(f"{owner}.{name}={value!r} must be an integer in [0, {high}]") from None
    if not 0 <= x <= high:
        raise ValueError(f"{owner}.{name}={x} is outside the allowed range [0, {high}]")


def _check_float(owner: str, name: str, value: object, fmt: struct.Struct) -> None:
    try:
        fmt.pack(value)
    except (struct.error, OverflowError, TypeError):
        width = "float32 (|value| <= 3.4028235e+38)" if fmt is _F32 else "float64"
        raise ValueError(
            f"{owner}.{name}={value!r} does not fit a {width}; NaN and ±inf are allowed"
        ) from None


@dataclass(frozen=True)
class Command:
    """Pressure set-points, PC → device (type 0x01).

    On the wire the pressures are float32, so a decoded Command carries the float32-rounded values.
    """

    TYPE: ClassVar[int] = MSG_COMMAND

    seq: int  # [-] u32 message counter
    device_time_us: int  # [µs] u64 timestamp
    pe_Pa: float  # [Pa] extensor gauge pressure set-point P'_e (float32 on the wire)
    pf_Pa: float  # [Pa] flexor gauge pressure set-point P'_f (float32 on the wire)

    def __post_init__(self) -> None:
        _check_uint("Command", "seq", self.seq, _U32_MAX)
        _check_uint("Command", "device_time_us", self.device_time_us, _U64_MAX)
        _check_float("Command", "pe_Pa", self.pe_Pa, _F32)
        _check_float("Command", "pf_Pa", self.pf_Pa, _F32)

    def _payload(self) -> bytes:
        return _COMMAND.pack(self.pe_Pa, self.pf_Pa)


@dataclass(frozen=True)
class Vent:
    """Vent both MPAs to atmosphere, PC → device (type 0x02, empty payload)."""

    TYPE: ClassVar[int] = MSG_VENT

    seq: int  # [-] u32 message counter
    device_time_us: int  # [µs] u64 timestamp

    def __post_init__(self) -> None:
        _check_uint("Vent", "seq", self.seq, _U32_MAX)
        _check_uint("Vent", "device_time_us", self.device_time_us, _U64_MAX)

    def _payload(self) -> bytes:
        return b""


@dataclass(frozen=True)
class Telemetry:
    """Measured state, device → PC (type 0x81)."""

    TYPE: ClassVar[int] = MSG_TELEMETRY

    seq: int  # [-] u32 message counter
    device_time_us: int  # [µs] u64 device clock when the sample was taken
    x_m: float  # [m] hip height X (float64 on the wire)
    v_mps: float  # [m/s] hip velocity V (float32 on the wire)
    pe_Pa: float  # [Pa] measured extensor gauge pressure P'_e (float32 on the wire)
    pf_Pa: float  # [Pa] measured flexor gauge pressure P'_f (float32 on the wire)
    faults: int  # [-] u16 bit set of FAULT_* flags
    ack_seq: int = 0  # [-] u32 seq of the last Command applied (0: none yet); gives latency

    def __post_init__(self) -> None:
        _check_uint("Telemetry", "seq", self.seq, _U32_MAX)
        _check_uint("Telemetry", "device_time_us", self.device_time_us, _U64_MAX)
        _check_float("Telemetry", "x_m", self.x_m, _F64)
        _check_float("Telemetry", "v_mps", self.v_mps, _F32)
        _check_float("Telemetry", "pe_Pa", self.pe_Pa, _F32)
        _check_float("Telemetry", "pf_Pa", self.pf_Pa, _F32)
        _check_uint("Telemetry", "faults", self.faults, _U16_MAX)
        _check_uint("Telemetry", "ack_seq", self.ack_seq, _U32_MAX)

    def _payload(self) -> bytes:
        return _TELEMETRY.pack(self.x_m, self.v_mps, self.pe_Pa, self.pf_Pa, self.faults,
                               self.ack_seq)


Message = Command | Vent | Telemetry


def fault_names(faults: int) -> tuple[str, ...]:
    """Names of the bits set in ``faults``, e.g. ``("watchdog_vent", "vented")``.

    Unknown bits are named by their value in hex (``"0x0010"``).
    """
    names = []
    for bit in range(16):
        flag = 1 << bit
        if faults & flag:
            names.append(_FAULT_NAMES.get(flag, f"0x{flag:04x}"))
    return tuple(names)


class _Spec(NamedTuple):
    name: str
    payload_size: int
    build: Callable[[int, int, bytes], Message]


_SPECS: dict[int, _Spec] = {
    MSG_COMMAND: _Spec(
        "Command", _COMMAND.size, lambda seq, t, p: Command(seq, t, *_COMMAND.unpack(p))
    ),
    MSG_VENT: _Spec("Vent", 0, lambda seq, t, p: Vent(seq, t)),
    MSG_TELEMETRY: _Spec(
        "Telemetry", _TELEMETRY.size, lambda seq, t, p: Telemetry(seq, t, *_TELEMETRY.unpack(p))
    ),
}
_KNOWN_TYPES = ", ".join(f"0x{t:02x} {spec.name}" for t, spec in _SPECS.items())


# --------------------------------------------------------------------------------------------
# Encoding and strict decoding


def encode(msg: Message) -> bytes:
    """The frame (sync .. crc) carrying ``msg``."""
    if not isinstance(msg, Command | Vent | Telemetry):
        raise TypeError(f"cannot encode {type(msg).__name__}; expected Command, Vent or Telemetry")
    payload = msg._payload()
    body = _HEADER.pack(SYNC, msg.TYPE, msg.seq, msg.device_time_us, len(payload)) + payload
    return body + _CRC.pack(crc16_ccitt_false(body[len(SYNC) :]))


def decode_frame(data: bytes) -> Message:
    """Decode exactly one frame.

    Raises
    ------
    ProtocolError
        For any byte string that is not exactly one valid frame: bad sync, truncated, unknown type,
        length that does not match the type, trailing bytes, or CRC mismatch. No other exception
        is raised for any bytes-like input.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise TypeError(f"decode_frame needs bytes, got {type(data).__name__}")
    data = bytes(data)
    n = len(data)
    head = data[: len(SYNC)]
    if head != SYNC[: len(head)]:
        raise ProtocolError(f"bad sync {head.hex(' ')}, expected {SYNC.hex(' ')}")
    if n < HEADER_SIZE:
        raise ProtocolError(f"truncated frame: {n} bytes, the header alone is {HEADER_SIZE}")
    _, mtype, seq, device_time_us, length = _HEADER.unpack_from(data)
    spec = _SPECS.get(mtype)
    if spec is None:
        raise ProtocolError(f"unknown message type 0x{mtype:02x} (known: {_KNOWN_TYPES})")
    if length != spec.payload_size:
        raise ProtocolError(
            f"length mismatch for type 0x{mtype:02x} ({spec.name}): header says {length} bytes, "
            f"the type has {spec.payload_size}"
        )
    size = HEADER_SIZE + length + CRC_SIZE
    if n < size:
        raise ProtocolError(f"truncated frame: {n} bytes, a {spec.name} frame is {size}")
    if n > size:
        raise ProtocolError(f"{n - size} trailing bytes after a {size}-byte {spec.name} frame")
    (received,) = _CRC.unpack_from(data, size - CRC_SIZE)
    computed = crc16_ccitt_false(data[len(SYNC) : size - CRC_SIZE])
    if received != computed:
        raise ProtocolError(
            f"CRC mismatch in {spec.name} frame: frame carries 0x{received:04x}, "
            f"computed 0x{computed:04x}"
        )
    return spec.build(seq, device_time_us, data[HEADER_SIZE : size - CRC_SIZE])


# --------------------------------------------------------------------------------------------
# Streaming decoder


class FrameDecoder:
    """Incremental decoder for a byte stream (serial bytes or concatenated UDP datagrams).

    ``feed`` returns the messages completed by the new bytes and keeps a partial frame for the
    next call. It scans for :data:`SYNC`; a candidate frame with an unknown type, a length that
    does not match its type, or a bad CRC is counted in :attr:`corrupt` and the scan resumes at the
    byte after its sync, so a real frame hidden behind a false sync is still found.

    Counters (cumulative, all ``int``):

    - ``corrupt``: candidate frames rejected (type, length or CRC).
    - ``skipped_bytes``: bytes discarded that were not part of a decoded frame (garbage and the
      remains of corrupt frames).
    - ``dropped_bytes``: bytes discarded unscanned because the buffer exceeded
      ``max_buffer_bytes``; the oldest go first.

    Every byte fed ends up in exactly one place: a decoded frame, ``skipped_bytes``,
    ``dropped_bytes``, or the retained buffer (less than one frame).

    Parameters
    ----------
    max_buffer_bytes
        Bound on the bytes held [B], 64 KiB by default. Complete frames are parsed during
        ``feed``, so between calls the buffer holds less than :data:`MAX_FRAME_SIZE` bytes; the
        bound caps the work of a single huge ``feed``, keeping its newest bytes.
    """

    def __init__(self, max_buffer_bytes: int = 64 * 1024) -> None:
        if max_buffer_bytes < MAX_FRAME_SIZE:
            raise ValueError(
                f"max_buffer_bytes={max_buffer_bytes} must be >= {MAX_FRAME_SIZE} "
                "(the largest frame)"
            )
        self.max_buffer_bytes = max_buffer_bytes
        self.corrupt = 0
        self.skipped_bytes = 0
        self.dropped_bytes = 0
        self._buf = bytearray()

    @property
    def buffered_bytes(self) -> int:
        """Bytes held for the next ``feed`` (a partial frame or a trailing first sync byte)."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop the buffered bytes (counted as skipped); the counters keep their values."""
        self.skipped_bytes += len(self._buf)
        self._buf.clear()

    def feed(self, data: bytes) -> list[Message]:
        """Add ``data`` to the stream; return the messages it completes, oldest first."""
        buf = self._buf
        buf += data
        excess = len(buf) - self.max_buffer_bytes
        if excess > 0:
            del buf[:excess]
            self.dropped_bytes += excess

        out: list[Message] = []
        n = len(buf)
        pos = 0
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # Keep a trailing first sync byte: its partner may come with the next feed.
                keep_from = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                self.skipped_bytes += keep_from - pos
                pos = keep_from
                break
            self.skipped_bytes += start - pos
            pos = start
            if n - pos < HEADER_SIZE:
                break
            _, mtype, seq, device_time_us, length = _HEADER.unpack_from(buf, pos)
            spec = _SPECS.get(mtype)
            if spec is None or length != spec.payload_size:
                self._reject_candidate()
                pos += 1
                continue
            end = pos + HEADER_SIZE + length + CRC_SIZE
            if end > n:
                break
            (received,) = _CRC.unpack_from(buf, end - CRC_SIZE)
            if received != crc16_ccitt_false(buf[pos + len(SYNC) : end - CRC_SIZE]):
                self._reject_candidate()
                pos += 1
                continue
            payload = bytes(buf[pos + HEADER_SIZE : end - CRC_SIZE])
            out.append(spec.build(seq, device_time_us, payload))
            pos = end
        del buf[:pos]
        return out

    def _reject_candidate(self) -> None:
        self.corrupt += 1
        self.skipped_bytes += 1  # its first sync byte; the rest is rescanned
