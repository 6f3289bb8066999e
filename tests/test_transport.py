"""Transports: pty <-> serial and UDP round trips, recv timeouts, errors that say what to check."""

from __future__ import annotations

import socket
import sys
import time
from collections.abc import Iterator

import pytest

from mpa_gym.hardware.protocol import Command, FrameDecoder, Telemetry, encode
from mpa_gym.hardware.transport import (
    PtyPair,
    SerialTransport,
    Transport,
    TransportError,
    UDPServer,
    UDPTransport,
    open_transport,
)

pytest.importorskip("serial")
posix_only = pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")

TIMEOUT_SLACK_S = 0.05  # [s] allowed overshoot of recv(timeout_s)


def recv_exactly(transport: Transport, n: int, within_s: float = 2.0) -> bytes:
    """Collect ``n`` bytes (a stream may deliver them in pieces) or fail after ``within_s``."""
    data = b""
    deadline = time.monotonic() + within_s
    while len(data) < n and time.monotonic() < deadline:
        data += transport.recv(0.05)
    return data


@pytest.fixture
def pty_link() -> Iterator[tuple[PtyPair, SerialTransport]]:
    with PtyPair() as pty, SerialTransport(pty.slave_path) as serial_end:
        yield pty, serial_end


@pytest.fixture
def udp_link() -> Iterator[tuple[UDPServer, UDPTransport]]:
    with UDPServer() as server, UDPTransport(*server.address) as client:
        yield server, client


# --------------------------------------------------------------------------------------------
# Round trips


@posix_only
def test_pty_serial_round_trip_both_directions(pty_link) -> None:
    pty, serial_end = pty_link
    to_device = bytes(range(256)) * 4  # every byte value: the line must be raw (no echo, no CR/LF)
    serial_end.send(to_device)
    assert recv_exactly(pty, len(to_device)) == to_device
    to_pc = bytes(reversed(to_device))
    pty.send(to_pc)
    assert recv_exactly(serial_end, len(to_pc)) == to_pc
    assert pty.dropped_bytes == 0
    assert pty.recv(0.0) == b""  # nothing echoed back


def test_udp_round_trip_both_directions(udp_link) -> None:
    server, client = udp_link
    server.send(b"before any peer")  # nobody to answer yet: a no-op
    assert server.peer is None
    client.send(b"ping")
    assert recv_exactly(server, 4) == b"ping"
    assert server.peer == ("127.0.0.1", client.local_port)
    server.send(b"pong")
    assert recv_exactly(client, 4) == b"pong"


@posix_only
def test_frames_survive_the_pty_link(pty_link) -> None:
    pty, serial_end = pty_link
    commands = [Command(i, 1000 * i, 1.0e5 + i, 2.0e5) for i in range(50)]
    for c in commands:
        serial_end.send(encode(c))
    decoder, received = FrameDecoder(), []
    deadline = time.monotonic() + 2.0
    while len(received) < len(commands) and time.monotonic() < deadline:
        received += decoder.feed(pty.recv(0.05))
    assert received == commands
    reply = Telemetry(1, 123, 0.75, -0.5, 3.0e5, 0.0, 0)
    pty.send(encode(reply))
    assert FrameDecoder().feed(recv_exactly(serial_end, len(encode(reply)))) == [reply]


# --------------------------------------------------------------------------------------------
# Timeouts


@pytest.mark.parametrize("side", ["pty", "serial", "udp server", "udp client"])
@pytest.mark.parametrize("timeout_s", [0.0, 0.1])
def test_recv_returns_empty_within_timeout(side: str, timeout_s: float, request) -> None:
    if side in ("pty", "serial"):
        if sys.platform == "win32":
            pytest.skip("pseudo-terminals are POSIX")
        pty, serial_end = request.getfixturevalue("pty_link")
        transport: Transport = pty if side == "pty" else serial_end
    else:
        server, client = request.getfixturevalue("udp_link")
        transport = server if side == "udp server" else client
    start = time.monotonic()
    assert transport.recv(timeout_s) == b""
    elapsed = time.monotonic() - start
    assert timeout_s - 0.005 <= elapsed <= timeout_s + TIMEOUT_SLACK_S


@pytest.mark.parametrize("timeout_s", [-0.1, float("nan"), float("inf")])
def test_recv_rejects_bad_timeouts(udp_link, timeout_s: float) -> None:
    server, _ = udp_link
    with pytest.raises(ValueError, match="timeout_s="):
        server.recv(timeout_s)


# --------------------------------------------------------------------------------------------
# Errors


def test_nonexistent_serial_port_says_what_to_check() -> None:
    with pytest.raises(TransportError, match="Check that") as info:
        SerialTransport("/dev/does-not-exist-mpa-gym")
    assert "/dev/does-not-exist-mpa-gym" in str(info.value)
    assert "dialout" in str(info.value)


@posix_only
def test_serial_read_after_the_emulator_is_gone_raises() -> None:
    pty = PtyPair()
    with SerialTransport(pty.slave_path) as serial_end:
        pty.close()
        pty.close()  # idempotent
        with pytest.raises(TransportError, match="Check that"):
            serial_end.recv(0.2)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="ICMP errors on loopback")
def test_udp_to_a_port_nobody_listens_on_says_so() -> None:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    free_port = probe.getsockname()[1]
    probe.close()
    with UDPTransport("127.0.0.1", free_port) as client:
        client.send(b"anyone?")
        with pytest.raises(TransportError, match="Check that the device or emulator is running"):
            client.recv(0.5)


def test_unresolvable_udp_host_says_what_to_check() -> None:
    with pytest.raises(TransportError, match=r"could not resolve UDP host .*Check"):
        UDPTransport("no-such-host.invalid", 9000, open_timeout_s=2.0)


def test_udp_open_gives_up_after_the_timeout(monkeypatch) -> None:
    """A DNS lookup that hangs must not hang the caller: the open is bounded by open_timeout_s."""

    def hanging_lookup(*args, **kwargs):
        time.sleep(1.0)
        raise OSError("lookup finished too late")

    monkeypatch.setattr(socket, "getaddrinfo", hanging_lookup)
    start = time.monotonic()
    with pytest.raises(TransportError, match=r"no answer within 0\.1 s\. Check the host name"):
        UDPTransport("slow-dns.example", 9000, open_timeout_s=0.1)
    assert time.monotonic() - start < 0.1 + TIMEOUT_SLACK_S


def test_closed_transport_raises(udp_link) -> None:
    _, client = udp_link
    client.close()
    client.close()  # idempotent
    with pytest.raises(TransportError, match="is closed"):
        client.send(b"x")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"host": "127.0.0.1", "port": 0}, "port=0"),
        ({"host": "127.0.0.1", "port": 70_000}, "port=70000"),
        ({"host": "127.0.0.1", "port": 9000, "local_port": -1}, "local_port=-1"),
    ],
)
def test_udp_bad_ports_are_named(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        UDPTransport(**kwargs)


# --------------------------------------------------------------------------------------------
# URLs


@pytest.mark.parametrize(
    "url",
    [
        "",
        "tcp://127.0.0.1:9000",
        "udp://127.0.0.1",
        "udp://:9000",
        "udp://127.0.0.1:99999",
        "udp://127.0.0.1:9000?speed=1",
        "serial://",
        "serial://dev/ttyUSB0",
        "serial:///dev/ttyUSB0?baud=fast",
        "serial:///dev/ttyUSB0?parity=E",
    ],
)
def test_bad_urls_name_the_url_and_the_allowed_forms(url: str) -> None:
    with pytest.raises(ValueError) as info:
        open_transport(url)
    message = str(info.value)
    assert repr(url) in message
    assert "serial:///dev/ttyUSB0?baud=1000000" in message
    assert "udp://HOST:PORT" in message


def test_open_transport_udp() -> None:
    with UDPServer() as server:
        host, port = server.address
        with open_transport(f"udp://{host}:{port}") as client:
            assert isinstance(client, UDPTransport)
            client.send(b"hi")
            assert recv_exactly(server, 2) == b"hi"


@posix_only
@pytest.mark.parametrize("form", ["url", "plain path"])
def test_open_transport_serial(form: str) -> None:
    with PtyPair() as pty:
        url = f"serial://{pty.slave_path}?baud=115200" if form == "url" else pty.slave_path
        with open_transport(url) as serial_end:
            assert isinstance(serial_end, SerialTransport)
            assert serial_end.description.startswith(f"serial {pty.slave_path}")
            serial_end.send(b"ok")
            assert recv_exactly(pty, 2) == b"ok"
