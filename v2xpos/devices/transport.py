"""Byte-stream transports for live devices: a serial port (pyserial) or a TCP client, each read on
its own thread that stamps every chunk with the host's GPS time on arrival.

Stamping is what an RTKLIB TIMETAG file records for a logged stream (``v2xpos.datasets.timetag``):
after each read the thread takes ``now_gps()`` and hands ``(chunk, arrival_s)`` to the consumer;
every byte of the chunk had arrived by then. The stamp is late by the read's wake-up delay (the
OS, and the interpreter lock when another thread computes); consumers therefore use arrival times
only through lower envelopes and minima, never one at a time.

Optionally the stream is recorded: the bytes to ``record`` and a TIMETAG file ``record + ".tag"``
in the RTKLIB layout (60-byte header, uint32 tick, uint32 + float64 open time in GPST seconds
since 1970, then (uint32 ms since open, uint32 byte offset) per chunk), so that a field drive can
be replayed with ``v2xpos replay`` / ``v2xpos emulate`` like the shared recordings.

A port that fails (unplugged, emulator stopped, caster gone) is reopened every ``retry_s``; the
failures are counted in ``stats()``, never raised to the service.
"""
from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Callable

from v2xpos import timebase

log = logging.getLogger(__name__)

TIMETAG_HEADER_BYTES = 60


class TimeTagWriter:
    """Write a stream's bytes and its RTKLIB TIMETAG file (layout in the module docstring)."""

    def __init__(self, path: str | Path, open_gps_s: float):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.data = open(self.path, "wb")
        self.tag = open(str(self.path) + ".tag", "wb")
        self.open_gps_s = float(open_gps_s)
        header = b"TIMETAG RTKLIB demo5 (v2xpos devices)".ljust(TIMETAG_HEADER_BYTES, b"\0")
        since_1970 = self.open_gps_s + timebase.GPS_UNIX_OFFSET_S
        sec = int(since_1970 // 1)
        self.tag.write(header + struct.pack("<IId", int(time.monotonic() * 1000) & 0xFFFFFFFF, sec,
                                            since_1970 - sec))
        self.offset = 0

    def write(self, chunk: bytes, arrival_s: float) -> None:
        self.data.write(chunk)
        self.offset += len(chunk)
        ms = max(0, int(round((arrival_s - self.open_gps_s) * 1000)))
        self.tag.write(struct.pack("<II", ms & 0xFFFFFFFF, self.offset & 0xFFFFFFFF))

    def close(self) -> None:
        for f in (self.data, self.tag):
            try:
                f.close()
            except OSError:
                pass


class Transport:
    """Base: a reader thread calling ``on_chunk(chunk, arrival_s)``; ``write(data)`` to the device.

    Subclasses implement ``_open()``, ``_read() -> bytes`` (b"" on a read timeout; raise OSError on
    failure), ``_write(data)`` and ``_close()``.
    """

    kind = "transport"

    def __init__(self, name: str, now_gps: Callable[[], float], on_chunk: Callable[[bytes, float], None],
                 retry_s: float = 1.0, record: str | Path | None = None):
        self.name = name
        self.now_gps = now_gps
        self.on_chunk = on_chunk
        self.retry_s = float(retry_s)
        self.record = record
        self._writer: TimeTagWriter | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.connected = False
        self.bytes_in = 0
        self.chunks = 0
        self.bytes_out = 0
        self.write_errors = 0
        self.open_failures = 0
        self.disconnects = 0
        self.consumer_errors = 0
        self.last_error = ""
        self.last_arrival_s = float("nan")

    # ---------------------------------------------------------------- subclass hooks
    def _open(self) -> None:
        raise NotImplementedError

    def _read(self) -> bytes:
        raise NotImplementedError

    def _write(self, data: bytes) -> int:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    # ---------------------------------------------------------------- thread
    def start(self) -> "Transport":
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"v2xpos-dev-{self.name}", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.connected:
                try:
                    with self._lock:
                        self._open()
                        self.connected = True
                except (OSError, ValueError) as exc:
                    self.open_failures += 1
                    self.last_error = f"open: {exc}"
                    self._stop.wait(self.retry_s)
                    continue
            try:
                chunk = self._read()
            except (OSError, ValueError) as exc:   # pyserial's SerialException is an OSError
                if self._stop.is_set():
                    break
                self.disconnects += 1
                self.last_error = f"read: {exc}"
                self._drop()
                self._stop.wait(self.retry_s)
                continue
            if not chunk:
                continue
            t = self.now_gps()
            self.bytes_in += len(chunk)
            self.chunks += 1
            self.last_arrival_s = t
            if self.record is not None:
                if self._writer is None:
                    self._writer = TimeTagWriter(self.record, t)
                self._writer.write(chunk, t)
            try:
                self.on_chunk(chunk, t)
            except Exception as exc:  # a consumer bug must not kill the port; counted and shown
                self.consumer_errors += 1
                self.last_error = f"consumer: {exc!r}"
                log.exception("%s: consumer failed on a chunk", self.name)
        self._drop()

    def _drop(self) -> None:
        with self._lock:
            if self.connected:
                try:
                    self._close()
                except OSError:
                    pass
            self.connected = False

    def write(self, data: bytes) -> int:
        """Write ``data`` to the device (corrections into a receiver); bytes written, 0 when closed."""
        if not data:
            return 0
        with self._lock:
            if not self.connected:
                self.write_errors += 1
                return 0
            try:
                n = self._write(bytes(data))
            except (OSError, ValueError) as exc:
                self.write_errors += 1
                self.last_error = f"write: {exc}"
                return 0
        self.bytes_out += n
        return n

    def close(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._drop()
        if self._writer is not None:
            self._writer.close()

    def stats(self) -> dict:
        return {"kind": self.kind, "connected": self.connected, "bytes_in": self.bytes_in, "chunks": self.chunks,
                "bytes_out": self.bytes_out, "write_errors": self.write_errors, "open_failures": self.open_failures,
                "disconnects": self.disconnects, "consumer_errors": self.consumer_errors,
                "last_error": self.last_error, "last_arrival_s": self.last_arrival_s}


class SerialTransport(Transport):
    """A serial port (``/dev/ttyACM0``, ``/dev/ttyUSB0``, a pseudo-terminal) read with pyserial."""

    kind = "serial"

    def __init__(self, port: str, baud: int, name: str, now_gps, on_chunk, read_timeout_s: float = 0.1,
                 **kw):
        super().__init__(name, now_gps, on_chunk, **kw)
        self.port = port
        self.baud = int(baud)
        self.read_timeout_s = read_timeout_s
        self._ser = None

    def _open(self) -> None:
        import serial
        self._ser = serial.Serial(self.port, self.baud, timeout=self.read_timeout_s, write_timeout=0.5)

    def _read(self) -> bytes:
        ser = self._ser
        waiting = ser.in_waiting
        return ser.read(waiting if waiting else 1)

    def _write(self, data: bytes) -> int:
        n = self._ser.write(data)
        return int(n or 0)

    def _close(self) -> None:
        if self._ser is not None:
            self._ser.close()
            self._ser = None

    def stats(self) -> dict:
        return {**super().stats(), "port": self.port, "baud": self.baud}


class TcpTransport(Transport):
    """A TCP client to ``host:port`` (a receiver's TCP server, ser2net, the emulator with --tcp)."""

    kind = "tcp"

    def __init__(self, host: str, port: int, name: str, now_gps, on_chunk, read_timeout_s: float = 0.1,
                 connect_timeout_s: float = 2.0, **kw):
        super().__init__(name, now_gps, on_chunk, **kw)
        self.host = host
        self.port = int(port)
        self.read_timeout_s = read_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self._sock: socket.socket | None = None

    def _open(self) -> None:
        s = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        s.settimeout(self.read_timeout_s)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = s

    def _read(self) -> bytes:
        try:
            data = self._sock.recv(65536)
        except socket.timeout:
            return b""
        if not data:
            raise ConnectionResetError("peer closed the connection")
        return data

    def _write(self, data: bytes) -> int:
        self._sock.sendall(data)
        return len(data)

    def _close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def stats(self) -> dict:
        return {**super().stats(), "address": f"{self.host}:{self.port}"}


def parse_address(text: str, where: str) -> tuple[str, int]:
    """``"host:port"`` -> (host, port); ValueError naming ``where`` otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"{where}: expected 'host:port', got {text!r}")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"{where}: port {port!r} is not a number") from None
    if not 0 < p < 65536:
        raise ValueError(f"{where}: port {p} out of range 1..65535")
    return host.strip("[]"), p
