"""One live device stream: a transport (serial / TCP), a framer and the decoders of its format,
delivering records (``v2xpos.devices.records``) to a sink callable on the transport's thread.

Formats:

* ``ubx``: a u-blox receiver's port: UBX (NAV-PVT, NAV-RELPOSNED, ESF-MEAS/ESF-RAW) and the NMEA
  sentences it interleaves. Positions come from NAV-PVT; NMEA positions are used only until the
  first NAV-PVT (a receiver configured for NMEA output only still works), HDT always.
* ``nmea``: any NMEA 0183 receiver (GGA/RMC/GST/HDT).
* ``csv_g_dps_ms``: a line-based IMU in the recorded csv format.

Each format is a receiver decoder registered by name (``decoder_formats``): the built-in ones
above (``BUILTIN_DECODERS``), then every entry point of the group ``v2xpos.decoders``. A decoder is
built as ``factory(name, options)`` (``options``: ``StreamOptions``) and has ``framer`` (a
``StreamFramer`` or ``LineFramer``), ``decode(frame) -> list of records`` and ``parts`` (label ->
the decoders whose ``issues``, ``counts`` and ``samples`` the stream's ``stats()`` reports);
docs/extending.md adds one.

Transport spec (a table of the device source's config): ``port = "/dev/ttyACM0"`` with optional
``baud`` (default 115200), or ``tcp = "host:port"``; optional ``record = "path"`` (bytes +
TIMETAG, see ``transport``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from v2xpos import plugins
from v2xpos.devices.framing import NMEA, RTCM3, UBX, LineFramer, StreamFramer
from v2xpos.devices.imu_lines import CsvImuDecoder
from v2xpos.devices.nmea import NmeaDecoder
from v2xpos.devices.records import GnssEpoch, ReceiverTime
from v2xpos.devices.transport import SerialTransport, TcpTransport, Transport, parse_address
from v2xpos.devices.ubx import UbxDecoder

DECODER_GROUP = "v2xpos.decoders"
BUILTIN_DECODERS: dict[str, str] = {
    "ubx": "v2xpos.devices.stream:UbxReceiver",
    "nmea": "v2xpos.devices.stream:NmeaReceiver",
    "csv_g_dps_ms": "v2xpos.devices.stream:CsvImu",
}
STREAM_KEYS = ("format", "port", "baud", "tcp", "record", "esf_tick_s", "nmea_sd_by_fix_m", "nmea_vel_sd_mps")
DEFAULT_BAUD = 115200


def decoder_formats() -> dict[str, str]:
    """Every known stream format -> ``module:factory`` (built-in first, then entry points)."""
    return plugins.registered(DECODER_GROUP, BUILTIN_DECODERS)


@dataclass(frozen=True)
class StreamOptions:
    """The decoder options of a stream table (a decoder uses those it knows)."""
    esf_tick_s: float = 1e-3
    nmea_sd_by_fix_m: dict | None = None
    nmea_vel_sd_mps: float = 0.1


class UbxReceiver:
    """A u-blox receiver's port: UBX and the NMEA it interleaves; NMEA positions only until the first
    NAV-PVT. RTCM3 the receiver echoes is framed and counted only."""

    def __init__(self, name: str, options: StreamOptions):
        self.ubx = UbxDecoder(f"{name} (UBX)", esf_tick_s=options.esf_tick_s)
        self.nmea = NmeaDecoder(f"{name} (NMEA)", sd_by_fix_m=options.nmea_sd_by_fix_m,
                                vel_sd_mps=options.nmea_vel_sd_mps)
        self.framer = StreamFramer((UBX, NMEA, RTCM3), name)
        self.parts = {"ubx": self.ubx, "nmea": self.nmea}
        self._nav_pvt_seen = False

    def decode(self, frame) -> list:
        if frame.protocol == UBX:
            recs = self.ubx.decode(frame.raw, frame.arrival_s, frame.end_offset)
            if recs and isinstance(recs[0], GnssEpoch):
                self._nav_pvt_seen = True
            return recs
        if frame.protocol == NMEA:
            recs = self.nmea.decode(frame.raw, frame.arrival_s, frame.end_offset)
            return [r for r in recs if not isinstance(r, (GnssEpoch, ReceiverTime))] if self._nav_pvt_seen else recs
        return []


class NmeaReceiver:
    """Any NMEA 0183 receiver (GGA/RMC/GST/HDT)."""

    def __init__(self, name: str, options: StreamOptions):
        self.nmea = NmeaDecoder(f"{name} (NMEA)", sd_by_fix_m=options.nmea_sd_by_fix_m,
                                vel_sd_mps=options.nmea_vel_sd_mps)
        self.framer = StreamFramer((NMEA,), name)
        self.parts = {"nmea": self.nmea}

    def decode(self, frame) -> list:
        return self.nmea.decode(frame.raw, frame.arrival_s, frame.end_offset)


class CsvImu:
    """A line-based IMU in the recorded csv format (``v2xpos.devices.imu_lines``)."""

    def __init__(self, name: str, options: StreamOptions):
        self.imu = CsvImuDecoder(f"{name} (csv)")
        self.framer = LineFramer(name)
        self.parts = {"imu_csv": self.imu}

    def decode(self, frame) -> list:
        return self.imu.decode(frame.raw, frame.arrival_s, frame.end_offset)


class DeviceStream:
    """Transport + framer + decoders of one device; ``sink(record)`` gets every decoded record."""

    def __init__(self, name: str, fmt: str, transport: Transport | None, sink: Callable[[object], None],
                 esf_tick_s: float = 1e-3, nmea_sd_by_fix_m: dict | None = None, nmea_vel_sd_mps: float = 0.1):
        formats = decoder_formats()
        if fmt not in formats:
            raise ValueError(f"unknown stream format {fmt!r}; one of {list(formats)}")
        self.name = name
        self.format = fmt
        self.sink = sink
        self.transport = transport
        factory = plugins.load(formats[fmt], f"stream format {fmt!r}")
        self.decoder = factory(name, StreamOptions(esf_tick_s, nmea_sd_by_fix_m, nmea_vel_sd_mps))
        self.framer = self.decoder.framer
        self.records = 0

    def feed(self, chunk: bytes, arrival_s: float) -> None:
        """Frame and decode one chunk (called on the transport's thread, or directly in tests)."""
        for frame in self.framer.feed(chunk, arrival_s):
            for r in self.decoder.decode(frame):
                self.records += 1
                self.sink(r)

    def start(self) -> None:
        if self.transport is not None:
            self.transport.start()

    def write(self, data: bytes) -> int:
        return self.transport.write(data) if self.transport is not None else 0

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    def stats(self) -> dict:
        out = {"format": self.format, "records": self.records, "framing": self.framer.stats()}
        if self.transport is not None:
            out["transport"] = self.transport.stats()
        parts = self.decoder.parts
        for label, dec in parts.items():
            d = {"malformed": dec.issues.count, "malformed_examples": dec.issues.as_dict()["examples"]}
            if hasattr(dec, "counts"):
                d["messages"] = dict(dec.counts)
            if hasattr(dec, "samples"):
                d["samples"] = dec.samples
            out[label] = d
        out["malformed"] = self.framer.issues.count + sum(dec.issues.count for dec in parts.values())
        return out


def open_stream(table: dict, name: str, where: str, now_gps: Callable[[], float],
                sink: Callable[[object], None], resolve: Callable[[str], object] = lambda p: p) -> DeviceStream:
    """A DeviceStream from a stream table (keys in ``STREAM_KEYS``); ValueError naming ``where`` and
    the key. The transport is created but not started (``stream.start()``)."""
    from v2xpos.schema import check_choice, check_keys
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table like {{ format = \"ubx\", port = \"/dev/ttyACM0\" }}")
    check_keys(table, STREAM_KEYS, where)
    fmt = table.get("format")
    check_choice(fmt, list(decoder_formats()), f"{where}.format")
    if ("port" in table) == ("tcp" in table):
        raise ValueError(f"{where}: give exactly one of 'port' (serial device) or 'tcp' (\"host:port\")")
    baud = table.get("baud", DEFAULT_BAUD)
    if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
        raise ValueError(f"{where}.baud: expected a positive integer, got {baud!r}")
    record = table.get("record")
    if record is not None and not isinstance(record, str):
        raise ValueError(f"{where}.record: expected a file path")
    tick = table.get("esf_tick_s", 1e-3)
    if isinstance(tick, bool) or not isinstance(tick, (int, float)) or not tick > 0:
        raise ValueError(f"{where}.esf_tick_s: expected a positive number of seconds, got {tick!r}")
    sd_by_fix = table.get("nmea_sd_by_fix_m")
    sd_map = None
    if sd_by_fix is not None:
        from v2xpos.types import FixStatus
        if not isinstance(sd_by_fix, dict):
            raise ValueError(f"{where}.nmea_sd_by_fix_m: expected a table like {{ FIXED = 0.02, FLOAT = 0.3 }}")
        check_keys(sd_by_fix, tuple(FixStatus.__members__), f"{where}.nmea_sd_by_fix_m")
        sd_map = {}
        for k, v in sd_by_fix.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"{where}.nmea_sd_by_fix_m.{k}: expected a positive number [m]")
            sd_map[FixStatus[k]] = float(v)
    vel_sd = table.get("nmea_vel_sd_mps", 0.1)
    if isinstance(vel_sd, bool) or not isinstance(vel_sd, (int, float)) or not vel_sd > 0:
        raise ValueError(f"{where}.nmea_vel_sd_mps: expected a positive number [m/s]")
    stream = DeviceStream(name, fmt, None, sink, esf_tick_s=float(tick), nmea_sd_by_fix_m=sd_map,
                          nmea_vel_sd_mps=float(vel_sd))
    rec = str(resolve(record)) if record is not None else None
    if "port" in table:
        port = table["port"]
        if not isinstance(port, str) or not port:
            raise ValueError(f"{where}.port: expected a device path like \"/dev/ttyACM0\"")
        stream.transport = SerialTransport(str(port), baud, name, now_gps, stream.feed, record=rec)
    else:
        host, port = parse_address(table["tcp"], f"{where}.tcp")
        stream.transport = TcpTransport(host, port, name, now_gps, stream.feed, record=rec)
    return stream
