"""RTK corrections over the V2V link: the master relays RTCM3 to every slave, each slave writes it
into its receiver.

Without corrections no receiver reaches RTK fixed or float, and every pair is gated out. The
master takes RTCM3 from an NTRIP caster or from a base station's serial port / TCP stream
(``v2xpos.devices.rtcm``), checks every frame (CRC-24Q, message type; pyrtcm), counts it and
publishes it unaltered on ``v2xpos/<fleet>/corrections`` (one zenoh put per frame, reliable,
congestion control BLOCK, so frames arrive complete and in order). The attachment carries a
sequence number and the master's send time (``struct "<Qd"``) so that a slave sees gaps and the
link delay. A slave's :class:`CorrectionSink` re-checks each frame and writes it into its
receiver (``VehicleSource.write_corrections``).

Config, the ``[corrections]`` table (unknown keys rejected, naming the key)::

    # master, NTRIP caster
    [corrections]
    source = "ntrip"
    caster = "caster.example.net:2101"
    mountpoint = "MOUNT"
    user = "me"
    password = "secret"
    ntrip_version = 2                 # or 1
    gga = "$GPGGA,..."                 # optional: position for network-RTK casters
    # master, base station on a serial port / TCP
    source = "serial"                  # port = "/dev/ttyUSB1", baud = 115200
    source = "tcp"                     # tcp = "192.168.1.20:5018"
    # slave
    [corrections]
    receive = true

API for the services (the lead wires these in):

* master: ``relay = CorrectionRelay(cfg, link, fleet, local_write=source.write_corrections)``;
  ``relay.start()`` ... ``relay.stats()`` into the status ... ``relay.close()``. ``local_write``
  (optional) also feeds the master's own receiver.
* slave: ``sink = CorrectionSink(link, fleet, source.write_corrections)`` ... ``sink.stats()`` ...
  ``sink.close()``.

Both ``stats()`` give frames, bytes, per-type counts, malformed, ``age_s`` (time since the last
frame, None before one) and ``throughput_bps`` (bytes per second over the last ``rate_window_s``).
"""
from __future__ import annotations

import math
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from v2xpos.devices.rtcm import NtripClient, RtcmChecker
from v2xpos.schema import check_choice, check_keys
from v2xpos.wire import corrections_key

ATTACHMENT = struct.Struct("<Qd")
SOURCES = ("ntrip", "serial", "tcp")
KEYS = ("source", "caster", "mountpoint", "user", "password", "ntrip_version", "gga", "gga_interval_s",
        "port", "baud", "tcp", "receive", "key", "rate_window_s")


@dataclass
class CorrectionsConfig:
    """Parsed ``[corrections]`` table (module docstring). ``source`` None: no relay (a slave)."""
    source: str | None = None
    caster: tuple[str, int] | None = None
    mountpoint: str = ""
    user: str = ""
    password: str = ""
    ntrip_version: int = 2
    gga: str | None = None
    gga_interval_s: float = 10.0
    port: str | None = None
    baud: int = 115200
    tcp: tuple[str, int] | None = None
    receive: bool = False
    key: str | None = None
    rate_window_s: float = 10.0


def parse_corrections(table: dict, where: str = "[corrections]") -> CorrectionsConfig:
    """Validate a ``[corrections]`` table; ValueError naming ``where`` and the key."""
    from v2xpos.devices.transport import parse_address
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table")
    check_keys(table, KEYS, where)
    c = CorrectionsConfig()

    def text(k: str) -> str:
        v = table[k]
        if not isinstance(v, str):
            raise ValueError(f"{where}.{k}: expected a string, got {v!r}")
        return v

    src = table.get("source")
    if src is not None and src not in SOURCES:
        check_choice(src, SOURCES, f"{where}.source")
    c.source = src
    needs = {"ntrip": ("caster", "mountpoint"), "serial": ("port",), "tcp": ("tcp",)}.get(src, ())
    for k in needs:
        if k not in table:
            raise ValueError(f"{where}.{k}: missing (needed by source = {src!r})")
    allowed_by = {"caster": "ntrip", "mountpoint": "ntrip", "user": "ntrip", "password": "ntrip",
                  "ntrip_version": "ntrip", "gga": "ntrip", "gga_interval_s": "ntrip", "port": "serial",
                  "baud": "serial", "tcp": "tcp"}
    for k, s in allowed_by.items():
        if k in table and src != s:
            raise ValueError(f"{where}.{k}: only with source = {s!r}")
    if "caster" in table:
        c.caster = parse_address(text("caster"), f"{where}.caster")
    for k in ("mountpoint", "user", "password", "port", "key"):
        if k in table:
            setattr(c, k, text(k))
    if "gga" in table:
        c.gga = text("gga")
        if not c.gga.startswith("$"):
            raise ValueError(f"{where}.gga: expected an NMEA GGA sentence")
    if "tcp" in table:
        c.tcp = parse_address(text("tcp"), f"{where}.tcp")
    if "ntrip_version" in table:
        if table["ntrip_version"] not in (1, 2) or isinstance(table["ntrip_version"], bool):
            raise ValueError(f"{where}.ntrip_version: 1 or 2")
        c.ntrip_version = int(table["ntrip_version"])
    if "baud" in table:
        b = table["baud"]
        if isinstance(b, bool) or not isinstance(b, int) or b <= 0:
            raise ValueError(f"{where}.baud: expected a positive integer")
        c.baud = b
    for k in ("gga_interval_s", "rate_window_s"):
        if k in table:
            v = table[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"{where}.{k}: expected a positive number")
            setattr(c, k, float(v))
    if "receive" in table:
        if not isinstance(table["receive"], bool):
            raise ValueError(f"{where}.receive: expected true or false")
        c.receive = table["receive"]
    if c.source is None and not c.receive:
        raise ValueError(f"{where}: give source = {list(SOURCES)} (master relay) or receive = true (slave)")
    return c


class _Rate:
    """Bytes per second over a sliding window, and the time of the last frame."""

    def __init__(self, window_s: float, clock: Callable[[], float]):
        self.window_s = window_s
        self.clock = clock
        self.events: deque[tuple[float, int]] = deque()
        self.total = 0
        self.last_t: float | None = None
        self.lock = threading.Lock()

    def add(self, n: int) -> None:
        t = self.clock()
        with self.lock:
            self.events.append((t, n))
            self.total += n
            self.last_t = t
            self._expire(t)

    def _expire(self, t: float) -> None:
        while self.events and self.events[0][0] < t - self.window_s:
            self.total -= self.events.popleft()[1]

    def figures(self) -> dict:
        t = self.clock()
        with self.lock:
            self._expire(t)
            return {"age_s": None if self.last_t is None else t - self.last_t,
                    "throughput_bps": self.total / self.window_s}


class CorrectionRelay:
    """Master side: RTCM3 in (NTRIP / serial / TCP), checked frames out on the link (module doc)."""

    def __init__(self, cfg: CorrectionsConfig, link, fleet: str, local_write: Callable[[bytes], int] | None = None,
                 clock: Callable[[], float] = time.time):
        if cfg.source is None:
            raise ValueError("[corrections]: a relay needs a source")
        self.cfg = cfg
        self.key = cfg.key or corrections_key(fleet)
        self.link = link
        self.local_write = local_write
        self.clock = clock
        self.checker = RtcmChecker(f"corrections ({cfg.source})")
        self.rate = _Rate(cfg.rate_window_s, clock)
        self.pub = None
        self.seq = 0
        self.bytes_sent = 0
        self.publish_errors = 0
        self.local_bytes = 0
        self._lock = threading.Lock()
        self.input = self._make_input()

    def _make_input(self):
        c = self.cfg
        if c.source == "ntrip":
            return NtripClient(c.caster[0], c.caster[1], c.mountpoint, self.on_bytes, user=c.user,
                               password=c.password, version=c.ntrip_version, gga=c.gga,
                               gga_interval_s=c.gga_interval_s, now=self.clock)
        from v2xpos.devices.transport import SerialTransport, TcpTransport
        if c.source == "serial":
            return SerialTransport(c.port, c.baud, "corrections", self.clock, self.on_bytes)
        return TcpTransport(c.tcp[0], c.tcp[1], "corrections", self.clock, self.on_bytes)

    def start(self) -> "CorrectionRelay":
        if self.link is not None and self.pub is None:
            self.pub = self.link.publisher(self.key, block=True, express=True)
        self.input.start()
        return self

    def on_bytes(self, chunk: bytes, arrival_s: float) -> None:
        """Bytes from the input (called on its thread): frame, check, publish each frame."""
        with self._lock:
            for frame, _ in self.checker.feed(chunk, arrival_s):
                self.rate.add(len(frame))
                if self.pub is not None:
                    try:
                        self.pub.put(frame, attachment=ATTACHMENT.pack(self.seq, time.time()))
                        self.bytes_sent += len(frame)
                    except Exception:  # zenoh errors surface as several types; counted, the input goes on
                        self.publish_errors += 1
                self.seq += 1
                if self.local_write is not None:
                    self.local_bytes += int(self.local_write(frame) or 0)

    def stats(self) -> dict:
        return {"role": "relay", "key": self.key, "input": self.input.stats(), **self.checker.stats(),
                "frames_sent": self.seq, "bytes_sent": self.bytes_sent, "publish_errors": self.publish_errors,
                "local_bytes_written": self.local_bytes, **self.rate.figures()}

    def close(self) -> None:
        stop = getattr(self.input, "stop", None) or self.input.close
        stop()


class CorrectionSink:
    """Slave side: frames from the link re-checked and written into the receiver (module doc)."""

    def __init__(self, link, fleet: str, write: Callable[[bytes], int], key: str | None = None,
                 rate_window_s: float = 10.0, clock: Callable[[], float] = time.time):
        self.key = key or corrections_key(fleet)
        self.write = write
        self.clock = clock
        self.checker = RtcmChecker("corrections (link)")
        self.rate = _Rate(rate_window_s, clock)
        self.frames = 0
        self.bytes_written = 0
        self.write_shortfalls = 0
        self.gaps = 0
        self.missing_frames = 0
        self.bad_attachment = 0
        self.link_delay_s = math.nan
        self._next_seq: int | None = None
        self._lock = threading.Lock()
        self._sub = link.subscribe(self.key, self._on_sample) if link is not None else None

    def _on_sample(self, payload: bytes, key: str, attachment: bytes | None, t_arrival: float) -> None:
        self.on_frame(payload, attachment, t_arrival)

    def on_frame(self, payload: bytes, attachment: bytes | None, t_arrival: float | None = None) -> None:
        """One published frame (zenoh thread): check it, account for the sequence, write it."""
        with self._lock:
            if attachment is not None and len(attachment) == ATTACHMENT.size:
                seq, sent = ATTACHMENT.unpack(attachment)
                if self._next_seq is not None and seq != self._next_seq:
                    self.gaps += 1
                    self.missing_frames += max(0, seq - self._next_seq)
                self._next_seq = seq + 1
                self.link_delay_s = (t_arrival if t_arrival is not None else time.time()) - sent
            else:
                self.bad_attachment += 1
            frames = self.checker.feed(payload, self.clock())
            for frame, _ in frames:
                self.frames += 1
                self.rate.add(len(frame))
                n = int(self.write(frame) or 0)
                self.bytes_written += n
                if n < len(frame):
                    self.write_shortfalls += 1

    def stats(self) -> dict:
        return {"role": "sink", "key": self.key, **self.checker.stats(), "frames_written": self.frames,
                "bytes_written": self.bytes_written, "write_shortfalls": self.write_shortfalls, "gaps": self.gaps,
                "missing_frames": self.missing_frames, "bad_attachment": self.bad_attachment,
                "link_delay_s": None if math.isnan(self.link_delay_s) else self.link_delay_s, **self.rate.figures()}

    def close(self) -> None:
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:  # already undeclared with the session
                pass
            self._sub = None
