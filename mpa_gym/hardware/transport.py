"""Byte transports between the PC and the rig: serial (pyserial) and UDP, plus emulator ends.

| class             | side     | link                                                        |
|-------------------|----------|-------------------------------------------------------------|
| SerialTransport   | PC       | a serial port or pseudo-terminal via pyserial               |
| UDPTransport      | PC       | a connected UDP socket to the device                        |
| UDPServer         | emulator | a bound UDP socket answering the last peer                  |
| PtyPair           | emulator | the master end of a pseudo-terminal; the PC opens its slave |

All four implement :class:`Transport`: ``send(data)``, ``recv(timeout_s)`` that returns whatever
bytes arrived within ``timeout_s`` (``b""`` if none) and never blocks longer, ``close()``,
``description`` and the context-manager protocol. Framing is the protocol's job
(:class:`mpa_gym.hardware.protocol.FrameDecoder`); a transport moves bytes only.

Failures raise :class:`TransportError` with a message that says what to check. Use
:func:`open_transport` to open the PC side from a URL (``serial:///dev/ttyUSB0?baud=1000000``,
a plain device path, or ``udp://HOST:PORT``).
"""

from __future__ import annotations

import errno
import math
import os
import select
import socket
import threading
import time
import tty
import urllib.parse
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import TypeVar

__all__ = [
    "PtyPair",
    "SerialTransport",
    "Transport",
    "TransportError",
    "UDPServer",
    "UDPTransport",
    "open_transport",
]

DEFAULT_BAUDRATE = 1_000_000  # [baud]
_MAX_DATAGRAM = 65_535  # [B] largest UDP payload read at once
_URL_FORMS = "'serial:///dev/ttyUSB0?baud=1000000' (or a plain device path) or 'udp://HOST:PORT'"

_T = TypeVar("_T")


class TransportError(ConnectionError):
    """A link to the rig could not be opened or failed; the message says what to check."""


def _check_timeout(name: str, value: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not a number") from None
    if not (math.isfinite(x) and x >= 0.0):
        raise ValueError(f"{name}={value!r} must be finite and >= 0 [s]")
    return x


def _check_port(name: str, value: int, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= 65_535:
        raise ValueError(f"{name}={value!r} must be an integer in [{low}, 65535]")
    return value


def _call_with_timeout(fn: Callable[[], _T], timeout_s: float, cleanup: Callable[[_T], None]) -> _T:
    """Run ``fn`` in a helper thread and wait at most ``timeout_s`` for it.

    Raises ``TimeoutError`` if it is still running; a result that arrives later is passed to
    ``cleanup`` (e.g. closes the port that finally opened), so nothing leaks.
    """
    lock = threading.Lock()
    outcome: list[tuple[bool, object]] = []
    abandoned = False

    def run() -> None:
        try:
            result: tuple[bool, object] = (True, fn())
        except BaseException as exc:  # handed to the caller below
            result = (False, exc)
        with lock:
            if not abandoned:
                outcome.append(result)
                return
        if result[0]:
            cleanup(result[1])  # type: ignore[arg-type]

    thread = threading.Thread(target=run, name="mpa_gym transport open", daemon=True)
    thread.start()
    thread.join(timeout_s)
    with lock:
        if not outcome:
            abandoned = True
            raise TimeoutError(f"no answer within {timeout_s:g} s")
    ok, value = outcome[0]
    if ok:
        return value  # type: ignore[return-value]
    raise value  # type: ignore[misc]


class Transport(ABC):
    """A bidirectional byte link. Subclasses implement ``send``, ``recv``, ``close`` and
    ``description``; ``with transport: ...`` closes it on exit."""

    @abstractmethod
    def send(self, data: bytes) -> None:
        """Send all of ``data``; raise :class:`TransportError` if the link fails."""

    @abstractmethod
    def recv(self, timeout_s: float) -> bytes:
        """Bytes that arrived within ``timeout_s`` [s] (``b""`` if none); never blocks longer.

        Returns as soon as some bytes are available, so the result may be a partial frame or
        several frames.
        """

    @abstractmethod
    def close(self) -> None:
        """Release the link; calling it again does nothing."""

    @property
    @abstractmethod
    def description(self) -> str:
        """Human-readable name of the link, e.g. ``"serial /dev/ttyUSB0 @ 1000000 baud"``."""

    def __enter__(self) -> Transport:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description}>"


# --------------------------------------------------------------------------------------------
# Serial


class SerialTransport(Transport):
    """A serial port through pyserial (``serial.serial_for_url``), non-blocking.

    Parameters
    ----------
    port
        Device path (``/dev/ttyUSB0``, ``/dev/ttyACM0``, a pseudo-terminal slave such as
        ``/dev/pts/3``, ``COM3``) or any pyserial URL (``socket://host:port``, ``loop://``).
    baudrate
        [baud] line speed; must match the firmware.
    open_timeout_s
        [s] bound on opening the port; also the write timeout of each ``send``.
    """

    def __init__(
        self, port: str, baudrate: int = DEFAULT_BAUDRATE, open_timeout_s: float = 2.0
    ) -> None:
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError(f"baudrate={baudrate!r} must be a positive integer [baud]")
        open_timeout_s = _check_timeout("open_timeout_s", open_timeout_s)
        try:
            import serial
        except ImportError as exc:
            raise TransportError(
                f"could not open serial port {port!r}: pyserial is not installed. "
                "Check your environment: pip install pyserial"
            ) from exc
        self._serial_exception = serial.SerialException
        self._serial_timeout = serial.SerialTimeoutException
        self._port = port
        self._baudrate = baudrate
        self._write_timeout_s = open_timeout_s
        hint = (
            "Check that the device is plugged in, that the path is right "
            "(ls /dev/ttyUSB* /dev/ttyACM*), and that you have permission (dialout group)"
        )
        try:
            self._serial = _call_with_timeout(
                lambda: serial.serial_for_url(
                    port, baudrate=baudrate, timeout=0, write_timeout=open_timeout_s
                ),
                open_timeout_s,
                cleanup=lambda s: s.close(),
            )
        except TimeoutError as exc:
            raise TransportError(
                f"could not open serial port {port!r}: no answer within {open_timeout_s:g} s. "
                f"{hint}"
            ) from exc
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"could not open serial port {port!r}: {exc}. {hint}") from exc
        try:
            self._fd: int | None = self._serial.fileno()
        except (AttributeError, OSError):  # URL handlers such as loop:// have no descriptor
            self._fd = None
        self._closed = False

    @property
    def description(self) -> str:
        return f"serial {self._port} @ {self._baudrate} baud"

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.description} is closed")

    def send(self, data: bytes) -> None:
        self._check_open()
        try:
            self._serial.write(data)
        except self._serial_timeout as exc:
            raise TransportError(
                f"write to {self.description} timed out after {self._write_timeout_s:g} s. "
                "Check that the device is running and reading, and the flow-control settings"
            ) from exc
        except (self._serial_exception, OSError) as exc:
            raise TransportError(
                f"write to {self.description} failed: {exc}. "
                "Check that the device is still plugged in"
            ) from exc

    def recv(self, timeout_s: float) -> bytes:
        self._check_open()
        deadline = time.monotonic() + _check_timeout("timeout_s", timeout_s)
        try:
            while True:
                waiting = self._serial.in_waiting
                if waiting:
                    return self._serial.read(waiting)
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return b""
                if self._fd is None:
                    time.sleep(min(remaining, 0.001))
                    continue
                ready, _, _ = select.select([self._fd], [], [], remaining)
                if ready:
                    # Readable with nothing waiting means a hang-up: pyserial raises on the read.
                    data = self._serial.read(self._serial.in_waiting or 1)
                    if data:
                        return data
        except (self._serial_exception, OSError) as exc:
            raise TransportError(
                f"read from {self.description} failed: {exc}. "
                "Check that the device is still plugged in (or the emulator still running)"
            ) from exc

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._serial.close()
        except (self._serial_exception, OSError):
            pass  # the device is gone already; nothing left to release


# --------------------------------------------------------------------------------------------
# UDP


def _drain_datagrams(sock: socket.socket, first: bytes) -> bytes:
    """``first`` plus every datagram already queued on the non-blocking ``sock``."""
    parts = [first]
    while True:
        try:
            parts.append(sock.recv(_MAX_DATAGRAM))
        except (BlockingIOError, InterruptedError):
            return b"".join(parts)


class UDPTransport(Transport):
    """A connected UDP socket to the device, non-blocking (``select`` for timeouts).

    UDP has no handshake: opening resolves the host and checks the address, nothing more; a
    device that is not there shows up as silence, or as "connection refused" on a later
    ``send``/``recv`` when the host answers with ICMP port-unreachable.

    Parameters
    ----------
    host, port
        The device's address.
    local_port
        Local UDP port to bind; 0 picks a free one.
    open_timeout_s
        [s] bound on resolving ``host`` (a DNS lookup can hang).
    """

    def __init__(
        self, host: str, port: int, local_port: int = 0, open_timeout_s: float = 2.0
    ) -> None:
        _check_port("port", port, 1)
        _check_port("local_port", local_port, 0)
        open_timeout_s = _check_timeout("open_timeout_s", open_timeout_s)
        self._host = host
        self._port = port
        where = f"{host}:{port}"
        try:
            infos = _call_with_timeout(
                lambda: socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM),
                open_timeout_s,
                cleanup=lambda _: None,
            )
        except TimeoutError as exc:
            raise TransportError(
                f"could not resolve UDP host {host!r}: no answer within {open_timeout_s:g} s. "
                "Check the host name (or use its IP address) and your DNS"
            ) from exc
        except (OSError, UnicodeError) as exc:
            raise TransportError(
                f"could not resolve UDP host {host!r}: {exc}. "
                "Check the host name or IP address of the device"
            ) from exc
        family, socktype, proto, _, address = infos[0]
        sock = socket.socket(family, socktype, proto)
        try:
            try:
                sock.bind(("::" if family == socket.AF_INET6 else "0.0.0.0", local_port))
            except OSError as exc:
                raise TransportError(
                    f"could not bind local UDP port {local_port}: {exc}. "
                    "Check that no other program uses it, or pass local_port=0"
                ) from exc
            try:
                sock.connect(address)
            except OSError as exc:
                raise TransportError(
                    f"could not connect UDP socket to {where}: {exc}. "
                    f"Check the host and port, that the network is up, and that the firewall "
                    f"allows UDP to port {port}"
                ) from exc
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        self._sock = sock
        self._local_port = sock.getsockname()[1]
        self._closed = False

    @property
    def local_port(self) -> int:
        """The local UDP port the socket is bound to (the real one when created with 0)."""
        return self._local_port

    @property
    def description(self) -> str:
        return f"udp {self._host}:{self._port} (local port {self._local_port})"

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.description} is closed")

    def _refused(self, exc: OSError) -> TransportError:
        return TransportError(
            f"{self.description}: {exc} (ICMP port unreachable). Check that the device or "
            f"emulator is running and listening on UDP port {self._port}, that the host is "
            "right, and that the firewall allows UDP"
        )

    def send(self, data: bytes) -> None:
        self._check_open()
        try:
            self._sock.send(data)
        except ConnectionRefusedError as exc:
            raise self._refused(exc) from exc
        except (BlockingIOError, InterruptedError):
            pass  # socket buffer full: the datagram is lost, as UDP may lose any datagram
        except OSError as exc:
            raise TransportError(
                f"send on {self.description} failed: {exc}. "
                "Check the network and that the datagram is below the MTU"
            ) from exc

    def recv(self, timeout_s: float) -> bytes:
        self._check_open()
        timeout_s = _check_timeout("timeout_s", timeout_s)
        try:
            ready, _, _ = select.select([self._sock], [], [], timeout_s)
            if not ready:
                return b""
            try:
                first = self._sock.recv(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return b""
            return _drain_datagrams(self._sock, first)
        except ConnectionRefusedError as exc:
            raise self._refused(exc) from exc
        except OSError as exc:
            raise TransportError(f"recv on {self.description} failed: {exc}") from exc

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()


class UDPServer(Transport):
    """The emulator's UDP end: bound to ``(host, port)``, it answers the last peer heard from.

    ``port=0`` picks a free port; read it from :attr:`address`. ``send`` before any peer has
    spoken does nothing (there is nobody to answer yet).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        _check_port("port", port, 0)
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
            family, socktype, proto, _, address = infos[0]
            sock = socket.socket(family, socktype, proto)
        except (OSError, UnicodeError) as exc:
            raise TransportError(
                f"could not create UDP server on {host}:{port}: {exc}. Check the host address"
            ) from exc
        try:
            sock.bind(address)
        except OSError as exc:
            sock.close()
            raise TransportError(
                f"could not bind UDP server to {host}:{port}: {exc}. Check that no other program "
                "uses the port (or pass port=0) and that the address belongs to this machine"
            ) from exc
        sock.setblocking(False)
        self._sock = sock
        self._peer: tuple[str, int] | None = None
        self._closed = False

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the server is bound to (the real port when created with port 0)."""
        host, port = self._sock.getsockname()[:2]
        return host, port

    @property
    def peer(self) -> tuple[str, int] | None:
        """Address of the last peer heard from, ``None`` before the first datagram."""
        return self._peer

    @property
    def description(self) -> str:
        host, port = self.address
        peer = f"{self._peer[0]}:{self._peer[1]}" if self._peer else "none yet"
        return f"udp server {host}:{port} (peer {peer})"

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"UDP server {self.address} is closed")

    def recv(self, timeout_s: float) -> bytes:
        """Datagrams that arrived within ``timeout_s`` [s], concatenated, from any peer.

        Remembers the sender of the last datagram as the peer for :meth:`send`.
        """
        self._check_open()
        timeout_s = _check_timeout("timeout_s", timeout_s)
        ready, _, _ = select.select([self._sock], [], [], timeout_s)
        if not ready:
            return b""
        parts: list[bytes] = []
        while True:
            try:
                data, peer = self._sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return b"".join(parts)
            except ConnectionRefusedError:
                continue  # an ICMP error for an earlier send to a peer that has left
            parts.append(data)
            self._peer = peer[:2]

    def send(self, data: bytes) -> None:
        """Send ``data`` to the last peer; a no-op before any peer has been heard from."""
        self._check_open()
        if self._peer is None:
            return
        try:
            self._sock.sendto(data, self._peer)
        except (BlockingIOError, InterruptedError, ConnectionRefusedError):
            pass  # lost datagram or a peer that left: UDP semantics, the client copes
        except OSError as exc:
            raise TransportError(f"send on {self.description} failed: {exc}") from exc

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()


# --------------------------------------------------------------------------------------------
# Pseudo-terminal


class PtyPair(Transport):
    """A pseudo-terminal for the emulator: it uses the master end, the PC opens :attr:`slave_path`.

    The slave is put in raw mode (no echo, no line discipline) and kept open until :meth:`close`,
    so its settings hold and bytes sent before the PC opens it are buffered.

    Like a UART whose reader has stalled, ``send`` never blocks: bytes that do not fit in the
    kernel's pty buffer are dropped and counted in :attr:`dropped_bytes` (the PC's
    :class:`~mpa_gym.hardware.protocol.FrameDecoder` resynchronises after the cut).
    """

    def __init__(self) -> None:
        try:
            master_fd, slave_fd = os.openpty()
        except OSError as exc:
            raise TransportError(
                f"could not create a pseudo-terminal: {exc}. Check that /dev/ptmx is available "
                "(a POSIX system) and the open-file limit"
            ) from exc
        try:
            tty.setraw(slave_fd)
            self.slave_path: str = os.ttyname(slave_fd)
            os.set_blocking(master_fd, False)
        except BaseException:
            os.close(master_fd)
            os.close(slave_fd)
            raise
        self._master_fd = master_fd
        self._slave_fd = slave_fd
        self.dropped_bytes = 0
        self._closed = False

    @property
    def description(self) -> str:
        return f"pty master (slave {self.slave_path})"

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.description} is closed")

    def send(self, data: bytes) -> None:
        self._check_open()
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._master_fd, view)
            except InterruptedError:
                continue
            except BlockingIOError:
                break
            except OSError as exc:
                raise TransportError(f"write to {self.description} failed: {exc}") from exc
            view = view[written:]
        self.dropped_bytes += len(view)

    def recv(self, timeout_s: float) -> bytes:
        self._check_open()
        timeout_s = _check_timeout("timeout_s", timeout_s)
        ready, _, _ = select.select([self._master_fd], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self._master_fd, _MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no slave open (Linux reports hang-up as EIO)
                return b""
            raise TransportError(f"read from {self.description} failed: {exc}") from exc

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for fd in (self._master_fd, self._slave_fd):
            try:
                os.close(fd)
            except OSError as exc:
                if exc.errno not in (errno.EIO, errno.EBADF):
                    raise


# --------------------------------------------------------------------------------------------
# URLs


def open_transport(url: str, timeout_s: float = 2.0) -> Transport:
    """Open the PC side of the link named by ``url``.

    Forms: ``serial:///dev/ttyUSB0?baud=1000000`` (``baud`` optional, default 1 000 000), a plain
    device path (``/dev/ttyUSB0``, ``COM3``), or ``udp://HOST:PORT`` (IPv6 as ``udp://[::1]:9000``;
    optional ``?local_port=N``). ``timeout_s`` [s] bounds the open.

    Raises ``ValueError`` naming the URL for anything else, and :class:`TransportError` when the
    link cannot be opened.
    """

    def bad(reason: str) -> ValueError:
        return ValueError(f"bad transport URL {url!r}: {reason}. Use {_URL_FORMS}")

    if not isinstance(url, str) or not url.strip():
        raise bad("not a non-empty string")
    if "://" not in url:
        return SerialTransport(url, open_timeout_s=timeout_s)
    parts = urllib.parse.urlsplit(url)
    try:
        query = urllib.parse.parse_qs(parts.query, keep_blank_values=True, strict_parsing=False)
    except ValueError as exc:
        raise bad(f"unreadable query ({exc})") from None

    def int_param(name: str, default: int) -> int:
        values = query.pop(name, None)
        if values is None:
            return default
        if len(values) != 1 or not values[0].strip().isdigit():
            raise bad(f"{name}={','.join(values)!r} is not a non-negative integer")
        return int(values[0])

    scheme = parts.scheme.lower()
    if scheme == "serial":
        if parts.netloc:
            raise bad(
                f"host part {parts.netloc!r} in a serial URL; use three slashes, e.g. "
                "serial:///dev/ttyUSB0"
            )
        path = parts.path
        if not path or path == "/":
            raise bad("no device path")
        if path[1:].upper().startswith("COM") and path[4:].isdigit():
            path = path[1:]  # serial:///COM3 on Windows
        baud = int_param("baud", DEFAULT_BAUDRATE)
        if baud <= 0:
            raise bad(f"baud={baud} must be > 0")
        if query:
            raise bad(f"unknown parameter(s) {sorted(query)} (allowed: baud)")
        return SerialTransport(path, baudrate=baud, open_timeout_s=timeout_s)
    if scheme == "udp":
        try:
            port = parts.port
        except ValueError as exc:
            raise bad(f"invalid port ({exc})") from None
        host = parts.hostname
        if not host:
            raise bad("no host")
        if port is None or port == 0:
            raise bad("no port (1-65535)")
        if parts.path not in ("", "/"):
            raise bad(f"unexpected path {parts.path!r}")
        local_port = int_param("local_port", 0)
        if local_port > 65_535:
            raise bad(f"local_port={local_port} must be in [0, 65535]")
        if query:
            raise bad(f"unknown parameter(s) {sorted(query)} (allowed: local_port)")
        return UDPTransport(host, port, local_port=local_port, open_timeout_s=timeout_s)
    raise bad(f"unknown scheme {parts.scheme!r}")
