"""RTCM3 correction streams: frame checks (pyrtcm), an NTRIP v1/v2 client and a checker that turns
any byte stream (caster, base-station serial port or TCP) into checked, unaltered frames.

Frame check (RTCM 10403.3 sec. 4; ``framing.StreamFramer``): preamble 0xD3, 6 reserved zero bits,
10-bit length, CRC-24Q over the whole frame (``pyrtcm.rtcmhelpers.calc_crc24q`` is 0 on a good
frame), message type = the first 12 bits of the message (DF002). A frame whose type pyrtcm does
not know (e.g. a proprietary 4072) is still relayed -- receivers ignore what they do not use --
and counted in ``unknown_types``. Frames are never re-encoded: the bytes relayed are the bytes
received.

NTRIP client (NTRIP 2.0, RTCM 10410.1; NTRIP 1.0 for old casters): ``GET /MOUNTPOINT`` with
``Authorization: Basic``, ``Ntrip-Version: Ntrip/2.0`` (v2, HTTP/1.1) or HTTP/1.0 (v1); the
caster answers ``HTTP/1.1 200 OK`` (v2, possibly ``Transfer-Encoding: chunked``) or ``ICY 200 OK``
(v1), then streams RTCM3. An optional GGA sentence (for network-RTK casters that need the rover
position) is sent in the ``Ntrip-GGA`` header (v2) or after the request (v1) and every
``gga_interval_s``. Why not pygnssutils' GNSSNTRIPClient: in version 1.3.1 its ``_do_request``
drops the body bytes that arrive with the response header and the first chunk read after it (the
``data`` of that ``recv`` is never handed to the parser), so "every byte that goes in arrives"
cannot hold; this client is small and keeps every byte.
"""
from __future__ import annotations

import base64
import socket
import threading
import time
from collections import Counter
from typing import Callable

from pyrtcm import RTCM_MSGIDS

from v2xpos.devices.framing import RTCM3, StreamFramer


def rtcm_message_type(frame: bytes) -> int:
    """DF002 message number of a framed RTCM3 message (first 12 bits after the 3-byte header)."""
    return ((frame[3] << 4) | (frame[4] >> 4)) if len(frame) >= 5 else -1


class RtcmChecker:
    """Frame a byte stream into checked RTCM3 frames; ``feed(chunk, arrival_s) -> [(frame, type)]``.

    Counts: frames and bytes per message type, malformed (bad CRC, bad header; with reasons),
    bytes between frames, unknown types.
    """

    def __init__(self, name: str = "rtcm"):
        self.framer = StreamFramer((RTCM3,), name)
        self.by_type: Counter = Counter()
        self.bytes_by_type: Counter = Counter()
        self.unknown_types = 0
        self.frames = 0
        self.bytes = 0

    def feed(self, chunk: bytes, arrival_s: float) -> list[tuple[bytes, int]]:
        out = []
        for f in self.framer.feed(chunk, arrival_s):
            mtype = rtcm_message_type(f.raw)
            if str(mtype) not in RTCM_MSGIDS:
                self.unknown_types += 1
            self.by_type[mtype] += 1
            self.bytes_by_type[mtype] += len(f.raw)
            self.frames += 1
            self.bytes += len(f.raw)
            out.append((f.raw, mtype))
        return out

    def stats(self) -> dict:
        fs = self.framer.stats()
        return {"frames": self.frames, "bytes": self.bytes, "by_type": {str(k): v for k, v in sorted(self.by_type.items())},
                "malformed": fs["malformed"], "malformed_examples": fs["malformed_examples"],
                "skipped_bytes": fs["skipped_bytes"], "unknown_types": self.unknown_types}


class NtripClient:
    """NTRIP v1/v2 client on a thread; ``on_chunk(bytes, arrival_s)`` gets the RTCM body bytes.

    Reconnects every ``retry_s`` after a failure; ``stats()`` says connected, bytes, reconnects,
    the last HTTP status and error. ``now`` stamps arrivals (GPS seconds of the host clock).
    """

    def __init__(self, host: str, port: int, mountpoint: str, on_chunk: Callable[[bytes, float], None],
                 user: str = "", password: str = "", version: int = 2, gga: str | None = None,
                 gga_interval_s: float = 10.0, now: Callable[[], float] = time.time, retry_s: float = 2.0,
                 timeout_s: float = 10.0):
        if version not in (1, 2):
            raise ValueError("NTRIP version must be 1 or 2")
        self.host, self.port, self.mountpoint = host, int(port), mountpoint.lstrip("/")
        self.on_chunk = on_chunk
        self.user, self.password = user, password
        self.version = version
        self.gga = gga
        self.gga_interval_s = float(gga_interval_s)
        self.now = now
        self.retry_s = float(retry_s)
        self.timeout_s = float(timeout_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self.connected = False
        self.bytes_in = 0
        self.connects = 0
        self.failures = 0
        self.status_line = ""
        self.last_error = ""

    def request(self) -> bytes:
        """The HTTP request this client sends (v2: HTTP/1.1 + Ntrip-Version; v1: HTTP/1.0)."""
        lines = [f"GET /{self.mountpoint} HTTP/{'1.1' if self.version == 2 else '1.0'}",
                 f"Host: {self.host}:{self.port}", "User-Agent: NTRIP v2xpos", "Accept: */*"]
        if self.user or self.password:
            cred = base64.b64encode(f"{self.user}:{self.password}".encode()).decode()
            lines.append(f"Authorization: Basic {cred}")
        if self.version == 2:
            lines.append("Ntrip-Version: Ntrip/2.0")
            if self.gga:
                lines.append(f"Ntrip-GGA: {self.gga.strip()}")
        lines.append("Connection: close")
        req = ("\r\n".join(lines) + "\r\n\r\n").encode()
        if self.version == 1 and self.gga:
            req += self.gga.strip().encode() + b"\r\n"
        return req

    def start(self) -> "NtripClient":
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="v2xpos-ntrip", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._session()
            except (OSError, ValueError) as exc:
                self.last_error = str(exc)
            self.connected = False
            if self._sock is not None:
                try:
                    self._sock.close()
                except OSError:
                    pass
                self._sock = None
            if not self._stop.is_set():
                self.failures += 1
                self._stop.wait(self.retry_s)

    def _deliver(self, data: bytes) -> None:
        if data:
            self.bytes_in += len(data)
            self.on_chunk(data, self.now())

    def _session(self) -> None:
        s = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        self._sock = s
        s.settimeout(0.5)
        s.sendall(self.request())
        head = b""
        deadline = time.monotonic() + self.timeout_s
        while b"\r\n\r\n" not in head and not head.startswith(b"ICY 200 OK\r\n"):
            if self._stop.is_set():
                return
            if time.monotonic() > deadline:
                raise TimeoutError("no response header from the caster")
            try:
                part = s.recv(4096)
            except socket.timeout:
                continue
            if not part:
                raise ConnectionResetError("caster closed the connection before answering")
            head += part
        sep = head.find(b"\r\n\r\n")
        if sep < 0:                          # "ICY 200 OK" + CR LF, then data (NTRIP 1.0 casters)
            header, body = head[:10], head[12:]
        else:
            header, body = head[:sep], head[sep + 4:]
        lines = header.decode("latin-1").split("\r\n")
        self.status_line = lines[0]
        parts = lines[0].split(" ")
        code = int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else 0
        headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:]) if _}
        if code != 200:
            raise ConnectionRefusedError(f"caster answered {lines[0]!r}")
        if "sourcetable" in headers.get("content-type", "") or parts[0].upper() == "SOURCETABLE":
            raise ConnectionRefusedError(f"mountpoint {self.mountpoint!r} not served (caster sent its sourcetable)")
        self.connected = True
        self.connects += 1
        chunked = "chunked" in headers.get("transfer-encoding", "").lower()
        dechunk = _Dechunker() if chunked else None
        last_gga = time.monotonic()
        pending = body
        while not self._stop.is_set():
            if pending:
                self._deliver(dechunk.feed(pending) if dechunk else pending)
                pending = b""
            if self.gga and self.gga_interval_s > 0 and time.monotonic() - last_gga >= self.gga_interval_s:
                s.sendall(self.gga.strip().encode() + b"\r\n")
                last_gga = time.monotonic()
            try:
                pending = s.recv(65536)
            except socket.timeout:
                continue
            if not pending:
                raise ConnectionResetError("caster closed the stream")

    def stop(self) -> None:
        self._stop.set()
        if self._sock is not None:
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        if self._thread is not None:
            self._thread.join(2.0)

    def stats(self) -> dict:
        return {"kind": "ntrip", "caster": f"{self.host}:{self.port}", "mountpoint": self.mountpoint,
                "version": self.version, "connected": self.connected, "bytes_in": self.bytes_in,
                "connects": self.connects, "failures": self.failures, "status_line": self.status_line,
                "last_error": self.last_error}


class _Dechunker:
    """HTTP/1.1 chunked transfer decoding (RFC 9112 sec. 7.1), incremental."""

    def __init__(self):
        self.buf = b""
        self.left = 0          # bytes of the current chunk still to pass
        self.skip_crlf = False

    def feed(self, data: bytes) -> bytes:
        self.buf += data
        out = bytearray()
        while self.buf:
            if self.left:
                take = self.buf[:self.left]
                out += take
                self.left -= len(take)
                self.buf = self.buf[len(take):]
                if not self.left:
                    self.skip_crlf = True
                continue
            if self.skip_crlf:
                if len(self.buf) < 2:
                    break
                self.buf = self.buf[2:]
                self.skip_crlf = False
                continue
            nl = self.buf.find(b"\r\n")
            if nl < 0:
                break
            size = int(self.buf[:nl].split(b";")[0].strip() or b"0", 16)
            self.buf = self.buf[nl + 2:]
            if size == 0:
                raise ConnectionResetError("caster ended the chunked stream")
            self.left = size
        return bytes(out)
