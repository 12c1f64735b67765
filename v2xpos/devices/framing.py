"""Incremental framing of a live byte stream into checked UBX, NMEA and RTCM3 frames, or into text
lines, with the arrival time of each frame's last byte.

A receiver's port interleaves several protocols (a u-blox receiver outputs UBX and NMEA on the
same port and echoes RTCM3 when asked); a base station or an NTRIP caster sends RTCM3 only. The
framer is fed chunks as the transport reads them and returns every frame that the chunk
completed; the frame's ``arrival_s`` is that chunk's arrival time, which is what an RTKLIB
TIMETAG file records for the frame's last byte (the time by which the byte had arrived).

Frame checks (the frame is dropped and counted in ``issues`` when they fail; the framer then
resynchronises one byte after the false start):

* UBX (u-blox Interface Description, "UBX frame structure"): ``B5 62 class id len16 payload
  CK_A CK_B``, 8-bit Fletcher checksum over class..payload; payload <= ``max_ubx_payload``.
* NMEA 0183: ``$`` .. ``*hh`` CR LF, hh = XOR of the characters between ``$`` and ``*``
  (``pynmeagps.nmeahelpers.calc_checksum``); at most ``max_nmea_bytes`` long.
* RTCM3 (RTCM 10403.3, sec. 4): ``D3``, 6 reserved zero bits, 10-bit length, message,
  CRC-24Q over header + message (``pyrtcm.rtcmhelpers.calc_crc24q``).

Bytes between frames (the stream was opened mid-frame, noise on the line) are counted in
``skipped_bytes``, not as malformed frames. A false sync whose declared length is plausible holds
the frames behind it back until that many bytes arrived (at most ``max_ubx_payload``); this is
the price of not guessing.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from pyrtcm.rtcmhelpers import calc_crc24q

from v2xpos.datasets.issues import ParseIssues

UBX, NMEA, RTCM3, LINE = "ubx", "nmea", "rtcm3", "line"
PROTOCOLS = (UBX, NMEA, RTCM3)
_SYNC = {UBX: rb"\xb5\x62", NMEA: rb"\$", RTCM3: rb"\xd3"}


@dataclass
class Frame:
    """One checked frame: protocol, its bytes, the host arrival time of its last byte [GPS s],
    and the stream offset just after it (bytes received since the port was opened)."""
    protocol: str
    raw: bytes
    arrival_s: float
    end_offset: int


def fletcher8(data: bytes | bytearray | memoryview) -> tuple[int, int]:
    """u-blox 8-bit Fletcher checksum (CK_A, CK_B) over ``data`` (class .. payload)."""
    a = b = 0
    for byte in data:
        a = (a + byte) & 0xFF
        b = (b + a) & 0xFF
    return a, b


def nmea_checksum_ok(line: bytes) -> bool:
    """True when an NMEA sentence ``$...*hh`` (CR LF optional) carries the XOR checksum of its body."""
    star = line.rfind(b"*")
    if star < 1 or len(line) < star + 3:
        return False
    x = 0
    for byte in line[1:star]:
        x ^= byte
    try:
        return int(line[star + 1:star + 3], 16) == x
    except ValueError:
        return False


_NMEA_SHAPE = re.compile(rb"\$[A-Z0-9]{3,}[^$*\r\n]*\*[0-9A-Fa-f]{2}\r?\n\Z")


class StreamFramer:
    """Feed chunks, get checked frames (see the module docstring).

    protocols: which of ``ubx``, ``nmea``, ``rtcm3`` to look for; name: the stream's name in the
    issue reports (a port or an address).
    """

    def __init__(self, protocols: tuple[str, ...] = PROTOCOLS, name: str = "stream",
                 max_ubx_payload: int = 8192, max_nmea_bytes: int = 256):
        unknown = set(protocols) - set(PROTOCOLS)
        if unknown:
            raise ValueError(f"unknown protocol(s) {sorted(unknown)}; known {PROTOCOLS}")
        self.protocols = tuple(protocols)
        self._sync = re.compile(b"|".join(_SYNC[p] for p in self.protocols))
        self._ubx_enabled = UBX in self.protocols
        self.buf = bytearray()
        self.base_offset = 0
        self.issues = ParseIssues(name)
        self.skipped_bytes = 0
        self.frames = {p: 0 for p in self.protocols}
        self.max_ubx_payload = max_ubx_payload
        self.max_nmea_bytes = max_nmea_bytes

    def _bad(self, start: int, reason: str) -> None:
        self.issues.add(self.base_offset + start, reason)

    def feed(self, data: bytes, arrival_s: float) -> list[Frame]:
        """Append a chunk that arrived at ``arrival_s`` and return the frames it completed."""
        self.buf += data
        buf = self.buf
        out: list[Frame] = []
        pos = 0
        n = len(buf)
        while pos < n:
            m = self._sync.search(buf, pos)
            if m is None:
                keep = 1 if self._ubx_enabled and buf[n - 1] == 0xB5 else 0   # half of a UBX sync
                self.skipped_bytes += n - keep - pos
                pos = n - keep
                break
            start = m.start()
            self.skipped_bytes += start - pos
            pos = start
            head = buf[start]
            if head == 0xB5:
                end, ok = self._ubx(start)
            elif head == 0x24:
                end, ok = self._nmea(start)
            else:
                end, ok = self._rtcm(start)
            if end is None:            # incomplete: wait for more bytes
                break
            if not ok:
                pos = start + 1
                continue
            proto = UBX if head == 0xB5 else NMEA if head == 0x24 else RTCM3
            self.frames[proto] += 1
            out.append(Frame(proto, bytes(buf[start:end]), arrival_s, self.base_offset + end))
            pos = end
        if pos:
            del buf[:pos]
            self.base_offset += pos
        return out

    # Each checker returns (end, ok): end None = incomplete; ok False = bad frame (counted).
    def _ubx(self, start: int) -> tuple[int | None, bool]:
        buf = self.buf
        if len(buf) - start < 6:
            return None, False
        length = buf[start + 4] | (buf[start + 5] << 8)
        if length > self.max_ubx_payload:
            self._bad(start, f"implausible UBX length {length}")
            return start + 1, False
        end = start + 8 + length
        if len(buf) < end:
            return None, False
        ck_a, ck_b = fletcher8(memoryview(buf)[start + 2:end - 2])
        if ck_a != buf[end - 2] or ck_b != buf[end - 1]:
            self._bad(start, f"UBX checksum mismatch (class 0x{buf[start + 2]:02x} id 0x{buf[start + 3]:02x})")
            return start + 1, False
        return end, True

    def _nmea(self, start: int) -> tuple[int | None, bool]:
        buf = self.buf
        nl = buf.find(b"\n", start, start + self.max_nmea_bytes)
        if nl < 0:
            if len(buf) - start >= self.max_nmea_bytes:
                self._bad(start, f"NMEA sentence without end of line within {self.max_nmea_bytes} bytes")
                return start + 1, False
            return None, False
        line = bytes(buf[start:nl + 1])
        nxt = line.find(b"$", 1)
        if nxt > 0:                    # a sentence cut short by the next one
            self._bad(start, f"NMEA sentence cut short: {line[:nxt][:40]!r}")
            return start + nxt, False
        if not _NMEA_SHAPE.match(line):
            self._bad(start, f"not an NMEA sentence: {line[:40]!r}")
            return start + 1, False
        if not nmea_checksum_ok(line):
            self._bad(start, f"NMEA checksum mismatch: {line[:40]!r}")
            return start + 1, False
        return nl + 1, True

    def _rtcm(self, start: int) -> tuple[int | None, bool]:
        buf = self.buf
        if len(buf) - start < 3:
            return None, False
        if buf[start + 1] & 0xFC:
            self._bad(start, "RTCM3 reserved bits not zero")
            return start + 1, False
        length = ((buf[start + 1] & 0x03) << 8) | buf[start + 2]
        end = start + 3 + length + 3
        if len(buf) < end:
            return None, False
        if calc_crc24q(bytes(buf[start:end])) != 0:
            self._bad(start, "RTCM3 CRC-24Q mismatch")
            return start + 1, False
        return end, True

    def stats(self) -> dict:
        """Frames per protocol, malformed frames (with the first reasons), bytes between frames."""
        return {"frames": dict(self.frames), "malformed": self.issues.count,
                "malformed_examples": self.issues.as_dict()["examples"], "skipped_bytes": self.skipped_bytes,
                "bytes": self.base_offset + len(self.buf)}


class LineFramer:
    """Split a text stream into lines (LF, CR LF), each with the arrival time of its LF.

    A line longer than ``max_line_bytes`` without LF is dropped and counted (a stream of binary
    noise must not grow the buffer without bound)."""

    def __init__(self, name: str = "stream", max_line_bytes: int = 512):
        self.buf = bytearray()
        self.base_offset = 0
        self.issues = ParseIssues(name)
        self.max_line_bytes = max_line_bytes
        self.lines = 0

    def feed(self, data: bytes, arrival_s: float) -> list[Frame]:
        self.buf += data
        out: list[Frame] = []
        pos = 0
        buf = self.buf
        while True:
            nl = buf.find(b"\n", pos)
            if nl < 0:
                if len(buf) - pos > self.max_line_bytes:
                    self.issues.add(self.base_offset + pos, f"line longer than {self.max_line_bytes} bytes")
                    pos = len(buf)
                break
            self.lines += 1
            out.append(Frame(LINE, bytes(buf[pos:nl + 1]), arrival_s, self.base_offset + nl + 1))
            pos = nl + 1
        if pos:
            del buf[:pos]
            self.base_offset += pos
        return out

    def stats(self) -> dict:
        return {"lines": self.lines, "malformed": self.issues.count,
                "malformed_examples": self.issues.as_dict()["examples"], "bytes": self.base_offset + len(self.buf)}
