"""A recording's real bytes as live devices, for tests and bench trials without hardware (the
``v2xpos emulate DATASET_TOML`` command is ``v2xpos.commands.emulate``).

Each byte stream of the recording that has an RTKLIB TIMETAG file -- the IMU csv (``[imu] file`` +
``timetag``), the raw u-blox stream (``[gnss] raw`` + ``raw_timetag``, or a ``[gnss]`` file of
format ``ubx`` with its ``timetag``) -- is written into its own pseudo-terminal (``os.openpty``,
raw mode; a ``device`` source opens the printed path like a serial port) or, with ``--tcp``, to
the clients of a TCP listener on 127.0.0.1 (port from the OS). The bytes go out in the recorded
chunks (one per TIMETAG record: the bytes that arrived between two records) at the recorded
arrival times, shifted onto the host clock and divided by ``--speed``.

Time. The recording's arrival times are GPS times in the past. The emulator fixes its timeline at
start: recorded time T0 (the first arrival) is written at host time H0 (``--start-in`` seconds
from now). A consumer must map its host clock onto the recording with
``gps = emulation_speed * host_gps + host_time_offset_s``, the two numbers printed (the
``clock`` table of the ``device`` source: ``host_time_offset_s``, ``emulation_speed``). They are
for emulation only; a vehicle runs on the real host clock. The minimum NAV-PVT latency of the
recording is printed too, as the ``latency_floor_s`` that makes the emulated receiver look
synchronised (see ``v2xpos.sources.gnss_clock``).

Why here (``v2xpos/devices``) and not a top-level ``bench/``: the emulator is the inverse of the
transports (same TIMETAG semantics, same pty/TCP endpoints) and uses only the formats floor, so
the library can ship it and the tests and the command import one module. Bytes due while no reader
is attached are dropped and counted (``counts()``); a reader that is slow delays the writes (a
pseudo-terminal holds about 4 kB), as a real port with flow control would.
"""
from __future__ import annotations

import errno
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from v2xpos import timebase


@dataclass
class EmulatedStream:
    """One device: its name, format, recorded chunks (arrival GPS s, bytes) and where it is served."""
    name: str
    format: str
    source: str
    times_s: np.ndarray
    chunks: list[bytes]
    vehicle: str = ""
    path: str = ""
    address: str = ""
    written: int = 0
    dropped: int = 0
    _master_fd: int = -1
    _slave_fd: int = -1
    _listener: socket.socket | None = None
    _clients: list = field(default_factory=list)


def timetag_chunks(data_path: str | Path, tag_path: str | Path) -> tuple[np.ndarray, list[bytes]]:
    """The recorded chunks of a TIMETAG'd file: for each record, the bytes that arrived since the
    previous record and its arrival time [GPS s]. Records that add no bytes are left out."""
    from v2xpos.datasets.timetag import read_timetag
    raw = Path(data_path).read_bytes()
    tag, _ = read_timetag(tag_path)
    offsets = np.minimum(tag.byte_offset, len(raw))
    times, chunks = [], []
    prev = 0
    for t, off in zip(tag.t_s, offsets):
        if off > prev:
            times.append(float(t))
            chunks.append(raw[prev:int(off)])
            prev = int(off)
    if prev < len(raw):                       # bytes after the last record: with the last one
        times.append(float(tag.t_s[-1]) if len(tag.t_s) else 0.0)
        chunks.append(raw[prev:])
    return np.asarray(times), chunks


def streams_of(toml_path: str | Path) -> list[EmulatedStream]:
    """The TIMETAG'd byte streams a dataset descriptor names (see module docstring)."""
    from v2xpos.datasets.loader import read_descriptor
    toml_path = Path(toml_path)
    desc = read_descriptor(toml_path)
    base = toml_path.parent
    out = []
    imu = desc.get("imu", {})
    if isinstance(imu, dict) and imu.get("file") and imu.get("timetag"):
        t, c = timetag_chunks(base / imu["file"], base / imu["timetag"])
        out.append(EmulatedStream("imu", imu.get("format", "csv_g_dps_ms"), str(base / imu["file"]), t, c))
    gnss = desc.get("gnss", {})
    if isinstance(gnss, dict):
        if gnss.get("raw") and gnss.get("raw_timetag"):
            t, c = timetag_chunks(base / gnss["raw"], base / gnss["raw_timetag"])
            out.append(EmulatedStream("gnss", "ubx", str(base / gnss["raw"]), t, c))
        elif gnss.get("format") == "ubx" and gnss.get("file") and gnss.get("timetag"):
            t, c = timetag_chunks(base / gnss["file"], base / gnss["timetag"])
            out.append(EmulatedStream("gnss", "ubx", str(base / gnss["file"]), t, c))
    return out


def vehicle_name(toml_path: Path, taken: dict) -> str:
    """A vehicle id for a recording: its descriptor's ``name`` (else its folder's), made unique."""
    from v2xpos.datasets.loader import read_descriptor
    name = str(read_descriptor(toml_path).get("name") or toml_path.parent.name or "vehicle")
    name = "".join(c if c.isalnum() or c in "_.-" else "_" for c in name)[:28] or "vehicle"
    base, k = name, 2
    while name in taken:
        name, k = f"{base}-{k}", k + 1
    return name


def min_nav_pvt_latency_s(stream: EmulatedStream, tag_path: str | Path | None) -> float | None:
    """Smallest NAV-PVT latency of a recorded UBX stream [s] (``datasets.ubx``), or None."""
    if stream.format != "ubx" or tag_path is None:
        return None
    from v2xpos.datasets.ubx import read_ubx
    res = read_ubx(stream.source, tag_path)
    lat = res.latency_s[np.isfinite(res.latency_s)]
    return float(lat.min()) if lat.size else None


def missing_streams(toml_path: str | Path) -> list[str]:
    """What a recording lacks for a ``device`` source (a GNSS byte stream and an IMU byte stream,
    each with its TIMETAG file), in words; empty when it can be served fully."""
    names = {s.name for s in streams_of(toml_path)}
    out = []
    if "gnss" not in names:
        out.append("no GNSS byte stream: [gnss] raw + raw_timetag (the receiver's u-blox stream and its TIMETAG) "
                   "or a [gnss] file of format \"ubx\" with its timetag (an RTKLIB .pos is a solution, not bytes)")
    if "imu" not in names:
        out.append("no IMU byte stream: [imu] file + timetag")
    return out


class Emulator:
    """Serve the streams of one or more recordings on one timeline (see module docstring).

    ``Emulator(toml or [toml, ...], speed=1.0, tcp=False, start_in_s=2.0, duration_s=None,
    only=None)``; after construction ``devices()`` (one recording) or ``vehicles()`` and ``timing()``
    say where and when; ``run()`` plays (blocking) until the end or ``stop()``. Several recordings
    of one drive (a convoy) share the timeline, so every consumer takes the same
    ``host_time_offset_s``.
    """

    def __init__(self, toml_path: str | Path | list, speed: float = 1.0, tcp: bool = False, start_in_s: float = 2.0,
                 duration_s: float | None = None, only: list[str] | None = None, skip_s: float = 0.0):
        if not speed > 0:
            raise ValueError("speed must be > 0")
        paths = [Path(p) for p in toml_path] if isinstance(toml_path, (list, tuple)) else [Path(toml_path)]
        self.toml_paths = paths
        self.toml_path = paths[0]
        self.speed = float(speed)
        self.tcp = tcp
        self.streams = []
        self.vehicle_ids: dict[str, Path] = {}
        for path in paths:
            vid = vehicle_name(path, self.vehicle_ids)
            self.vehicle_ids[vid] = path
            found = [s for s in streams_of(path) if only is None or s.name in only]
            if not found:
                raise ValueError(f"{path}: no byte stream with a TIMETAG file to emulate")
            for st in found:
                st.vehicle = vid
            self.streams += found
        self.t0_rec_s = min(float(s.times_s[0]) for s in self.streams if len(s.times_s)) + skip_s
        self.t_end_rec_s = max(float(s.times_s[-1]) for s in self.streams if len(s.times_s))
        if duration_s is not None:
            self.t_end_rec_s = min(self.t_end_rec_s, self.t0_rec_s + duration_s)
        self._stop = threading.Event()
        self.block_timeout_s = 1.0
        for s in self.streams:
            self._open(s)
        self.set_start(start_in_s)

    def set_start(self, start_in_s: float) -> None:
        """(Re)fix the timeline: the first recorded byte goes out ``start_in_s`` from now."""
        self.h0_unix_s = time.time() + float(start_in_s)
        self.host_time_offset_s = self.t0_rec_s - self.speed * float(timebase.unix_to_gps_seconds(self.h0_unix_s))

    def _open(self, s: EmulatedStream) -> None:
        if self.tcp:
            ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            ls.bind(("127.0.0.1", 0))
            ls.listen(4)
            ls.setblocking(False)
            s._listener = ls
            s.address = f"127.0.0.1:{ls.getsockname()[1]}"
        else:
            m, sl = os.openpty()
            tty.setraw(sl)              # binary bytes pass unchanged (no echo, no CR/LF mapping)
            os.set_blocking(m, False)
            s.path = os.ttyname(sl)
            os.close(sl)                # the master then polls POLLHUP until a reader opens the path
            s._master_fd = m

    def vehicles(self) -> dict:
        """{vehicle id: {"dataset": toml path, "devices": {name: {...}}}} of every recording served."""
        return {vid: {"dataset": str(path), "devices": self.devices(vid)} for vid, path in self.vehicle_ids.items()}

    def devices(self, vehicle: str | None = None) -> dict:
        """{name: {"format", "path" | "tcp", "source"}} of the served streams (of ``vehicle``; default
        the first recording)."""
        vehicle = next(iter(self.vehicle_ids)) if vehicle is None else vehicle
        out = {}
        for s in [s for s in self.streams if s.vehicle == vehicle]:
            d = {"format": s.format, "source": s.source}
            if s.path:
                d["port"] = s.path
            if s.address:
                d["tcp"] = s.address
            out[s.name] = d
        return out

    def timing(self) -> dict:
        """The numbers a consumer needs to put its host clock onto the recording (emulation only)."""
        return {"host_time_offset_s": self.host_time_offset_s, "emulation_speed": self.speed,
                "start_unix_s": self.h0_unix_s, "recording_start_gps_s": self.t0_rec_s,
                "recording_end_gps_s": self.t_end_rec_s}

    def _accept(self, s: EmulatedStream) -> None:
        if s._listener is None:
            return
        while True:
            try:
                c, _ = s._listener.accept()
            except (BlockingIOError, OSError):
                return
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            c.setblocking(False)
            s._clients.append(c)

    def _write(self, s: EmulatedStream, data: bytes) -> None:
        if s._master_fd >= 0:
            self._discard_echo(s)
            poller = select.poll()
            poller.register(s._master_fd, select.POLLOUT)
            view = memoryview(data)
            while view:
                ev = poller.poll(int(self.block_timeout_s * 1000))
                if not ev or ev[0][1] & select.POLLHUP or not ev[0][1] & select.POLLOUT:
                    s.dropped += len(view)        # no reader attached (or it stopped reading)
                    return
                try:
                    n = os.write(s._master_fd, view)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as exc:
                    if exc.errno == errno.EIO:
                        s.dropped += len(view)
                        return
                    raise
                s.written += n
                view = view[n:]
            return
        self._accept(s)
        if not s._clients:
            s.dropped += len(data)
            return
        for c in list(s._clients):
            try:
                c.sendall(data)
            except BlockingIOError:
                s.dropped += len(data)
            except OSError:
                s._clients.remove(c)
                c.close()
        s.written += len(data)

    @staticmethod
    def _discard_echo(s: EmulatedStream) -> None:
        """Drain what the reader wrote back into the pty (corrections into the 'receiver')."""
        while True:
            r, _, _ = select.select([s._master_fd], [], [], 0)
            if not r:
                return
            try:
                if not os.read(s._master_fd, 65536):
                    return
            except OSError:
                return

    def run(self) -> dict:
        """Play until the end of the recording (or ``duration``) or ``stop()``; returns counts."""
        events = []
        for k, s in enumerate(self.streams):
            for t, c in zip(s.times_s, s.chunks):
                if self.t0_rec_s <= t <= self.t_end_rec_s:
                    events.append((float(t), k, c))
        events.sort(key=lambda e: (e[0], e[1]))
        for t, k, c in events:
            if self._stop.is_set():
                break
            wall = self.h0_unix_s + (t - self.t0_rec_s) / self.speed
            delay = wall - time.time()
            if delay > 0 and self._stop.wait(delay):
                break
            self._write(self.streams[k], c)
        return self.counts()

    def counts(self) -> dict:
        """Bytes written and dropped per stream (``vehicle/stream`` when several recordings are served)."""
        several = len(self.vehicle_ids) > 1
        return {f"{s.vehicle}/{s.name}" if several else s.name: {"written": s.written, "dropped": s.dropped}
                for s in self.streams}

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self.stop()
        for s in self.streams:
            for fd in (s._master_fd, s._slave_fd):
                if fd >= 0:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            s._master_fd = s._slave_fd = -1
            for c in s._clients:
                c.close()
            if s._listener is not None:
                s._listener.close()
