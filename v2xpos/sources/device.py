"""The ``device`` source: a vehicle's live receiver and IMU through the GNSS/INS filter, on GPS time
from the host clock.

Config (the ``[source]`` table; paths relative to the config file)::

    [source]
    type = "device"
    platform = "car"                       # car | pedestrian | generic
    gnss = { format = "ubx", port = "/dev/ttyACM0", baud = 115200 }   # or { format = "nmea", tcp = "127.0.0.1:5000" }
    imu = { format = "csv_g_dps_ms", port = "/dev/ttyUSB0", baud = 115200 }   # or imu = "receiver" (ESF of an F9R)
    imu_to_body = [[-1, 0, 0], [0, 1, 0], [0, 0, -1]]   # v_body = imu_to_body @ v_imu (rotation), or "identity"
    lever_arm_m = [0.0, 0.0, -0.3]         # antenna - IMU in body axes (x fwd, y right, z down) [m]

``platform``, ``imu_to_body`` and ``lever_arm_m`` are required (``REQUIRED_KEYS``): a missing one is
refused naming the key; the identity mounting is declared as ``imu_to_body = "identity"``.
    lever_arm_sd_m = 0.02
    reorder_window_s = 0.5                 # how far back a late GNSS epoch is put in its place ("Time order")
    clock = { max_offset_s = 0.02, latency_floor_s = 0.025 }   # v2xpos.sources.gnss_clock
    [source.calibration]                    # optional, the [calibration] table of v2xpos.datasets.calibration

The filter configuration is the services' profile of the declared platform, mounting and lever
arm and the calibration table (``v2xpos.ins.profiles.vehicle_config``, the function ``v2xpos
replay`` and the ``recording`` source use).

Each stream table is ``v2xpos.devices.stream`` (``format``, ``port``/``baud`` or ``tcp``,
``record``...). Unknown keys are rejected naming the table and the key.

Data path: every stream is read on its own thread (``v2xpos.devices.transport``), framed, decoded
(pyubx2 / pynmeagps / the csv decoder) and stamped with the host's GPS arrival time; the records
wait in a queue until the service calls ``advance(t)``; each one queued wakes the service loop
(``wait_for_input``). IMU counters are mapped to GPS time by the online lower-envelope model of
their arrival stamps (``v2xpos.devices.clock_model``), as the
recorded reader maps a TIMETAG'd csv; receiver time statements go to the ``HostGnssClock``.

Time order. The records go to the one driver of the filter (``v2xpos.ins.driver.InsDriver``) as
they arrive -- each IMU sample mapped to GPS time, each GNSS epoch, each usable heading -- and the
driver processes them at once, in the order of their times of validity (the same rule as
``v2xpos replay``: a GNSS epoch after the IMU samples stamped <= t_gnss - imu_time_offset -
gnss_latency). A state is returned for each IMU sample as soon as it arrives; a reader thread that
queues a record wakes the service loop waiting in ``wait_for_input``, so a state leaves with the
IMU line that carried it, not at the loop's next 10 ms tick. A GNSS epoch reaches the host
20-80 ms after its time, after the IMU samples beyond it were processed: the driver puts it in
its place (it restores its snapshot of the filter from before the epoch and processes the samples
since again, ``reorder_window_s`` back at most, counted ``gnss_reordered``); the states already returned stay
as they were, the next ones include it. An epoch older than the window, or not newer than the
previous one, is counted (``gnss_rejected_late``, ``gnss_out_of_order``) and not used. A GNSS
epoch still waiting for IMU samples one second after its time is applied at the filter's state
(``gnss_without_imu``). States come with strictly increasing times.

Dual-antenna heading. NAV-RELPOSNED / HDT headings are decoded and reported in ``status()``. With
``heading_baseline_m = [x, y, z]`` (the vector from the primary to the secondary antenna in body
axes, x fwd y right z down [m]) in the table, each heading that has a time and an accuracy is
applied in time order with the GNSS epochs (``InsFilter.update_heading``): at a stop it sets the
heading the filter cannot otherwise know before the vehicle drives off, so results become VALID
without a guess; later it is a measurement. Without the key headings are not used: the baseline's
direction in the body is what turns an azimuth into a heading. Headings without a time (HDT) or
without an accuracy are counted (``headings_unusable``) and not used.
"""
from __future__ import annotations

import math
import threading
from collections import deque
from pathlib import Path

import numpy as np

from v2xpos.datasets.calibration import CalibrationError, parse_calibration
from v2xpos.devices.clock_model import OnlineLowerEnvelope
from v2xpos.devices.records import GnssEpoch, HeadingObs, ImuRecord, ReceiverTime
from v2xpos.devices.stream import DeviceStream, open_stream
from v2xpos.schema import check_choice, check_keys
from v2xpos.sources.base import SessionClock, SourceContext, SourceError, VehicleSource
from v2xpos.sources.gnss_clock import HostGnssClock, clock_from_config
from v2xpos.types import FixStatus, NavState

SOURCE_KEYS = ("gnss", "imu", "platform", "imu_to_body", "lever_arm_m", "lever_arm_sd_m", "reorder_window_s",
               "clock", "calibration", "imu_clock_min_span_s", "heading_baseline_m")
PLATFORMS = ("car", "pedestrian", "generic")
LATENCY_HISTORY = 1000
"""Advances whose input-to-state time ``status()["latency"]`` summarises."""
REQUIRED_KEYS = (
    ("platform", f"one of {list(PLATFORMS)} (the vehicle constraints the filter applies)"),
    ("imu_to_body", "the IMU mounting, v_body = imu_to_body @ v_imu, e.g. [[-1, 0, 0], [0, 1, 0], [0, 0, -1]]; "
                    "write imu_to_body = \"identity\" when the IMU axes are the body axes"),
    ("lever_arm_m", "the antenna relative to the IMU in body axes [m] (x forward, y right, z down), surveyed; "
                    "[0.0, 0.0, 0.0] only when they coincide"))
"""Keys a ``device`` table must declare: a mounting or lever arm left out is not silently the
identity or zero (a car with an undeclared x-backward IMU gives no VALID row at all)."""


def _matrix(value, shape: tuple, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SourceError(f"{where}: not numeric") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise SourceError(f"{where}: expected a finite array of shape {shape}, got {value!r}")
    return arr


class DeviceSource(VehicleSource):
    """Live streams through ``v2xpos.ins.InsFilter`` on the driver (see module docstring)."""

    name = "device"

    def __init__(self, gnss: DeviceStream, imu: DeviceStream | None, ins_config, clock: HostGnssClock,
                 reorder_window_s: float | None = None, imu_clock_min_span_s: float = 5.0, calibration=None,
                 heading_baseline_m: np.ndarray | None = None):
        from v2xpos.ins import InsFilter
        from v2xpos.ins.driver import REORDER_WINDOW_S, InsDriver
        if reorder_window_s is None:
            reorder_window_s = REORDER_WINDOW_S
        self.gnss_stream = gnss
        self.imu_stream = imu
        self.imu_source_name = imu.name if imu is not None else gnss.name
        self.cfg = ins_config
        self.kind = "pedestrian" if ins_config.setup.platform == "pedestrian" else "vehicle"
        self.filter = InsFilter(ins_config)
        self.driver = InsDriver(self.filter, reorder_window_s=float(reorder_window_s), emit_states=True)
        self.clock = clock
        self.reorder_window_s = float(reorder_window_s)
        self.imu_clock = OnlineLowerEnvelope(min_span_s=imu_clock_min_span_s)
        self.calibration = calibration
        self.inbox: deque = deque()
        self.input_arrived = threading.Event()   # set by the reader threads with each record (``wait_for_input``)
        self.last_gnss: GnssEpoch | None = None
        self.last_heading: HeadingObs | None = None
        self.heading_baseline_m = None if heading_baseline_m is None else np.asarray(heading_baseline_m, float)
        self._received = {"imu_samples": 0, "gnss_epochs": 0, "headings": 0, "headings_unusable": 0,
                          "ignored_imu_records": 0, "imu_clock_rejected": 0}
        self._last_input_arrival_s = math.nan
        self.input_to_state_s: deque = deque(maxlen=LATENCY_HISTORY)
        self._closed = False
        self._started = False

    # ------------------------------------------------------------------ plumbing

    def start(self) -> None:
        """Open the ports and start the reader threads (idempotent; ``from_config`` calls it)."""
        if self._started:
            return
        self._started = True
        self.gnss_stream.start()
        if self.imu_stream is not None:
            self.imu_stream.start()

    def make_clock(self, ctx: SourceContext | None = None) -> SessionClock:
        return self.clock

    def warm_up(self) -> None:
        """Compile the filter's jitted kernels (or load their cache) before real time starts."""
        from v2xpos.ins.driver import warm_up
        warm_up(self.cfg)

    # ------------------------------------------------------------------ records -> driver
    def _drain(self) -> None:
        inbox, drv = self.inbox, self.driver
        while inbox:
            stream_name, rec = inbox.popleft()
            if isinstance(rec, ImuRecord):
                if stream_name != self.imu_source_name:
                    self._received["ignored_imu_records"] += 1
                    continue
                if not self.imu_clock.add(rec.counter_s, rec.arrival_s):
                    self._received["imu_clock_rejected"] += 1
                    continue
                self._received["imu_samples"] += 1
                self._last_input_arrival_s = rec.arrival_s
                drv.push_imu(self.imu_clock.to_gps(rec.counter_s), rec.acc_mps2, rec.gyro_rps)
            elif isinstance(rec, GnssEpoch):
                self._received["gnss_epochs"] += 1
                self.last_gnss = rec
                self._last_input_arrival_s = rec.arrival_s
                drv.push_gnss(rec.t_s, rec.lla, rec.sd_ned_m, rec.fix, rec.vel_ned_mps, rec.vel_sd_ned_mps)
            elif isinstance(rec, ReceiverTime):
                self.clock.observe(rec.t_s, rec.arrival_s, rec.gps_minus_utc_s, rec.message)
            elif isinstance(rec, HeadingObs):
                self._received["headings"] += 1
                self.last_heading = rec
                if self.heading_baseline_m is None:
                    continue
                if not (math.isfinite(rec.t_s) and math.isfinite(rec.heading_sd_rad) and rec.heading_sd_rad > 0):
                    self._received["headings_unusable"] += 1
                    continue
                drv.push_heading(rec.t_s, rec.heading_rad, rec.heading_sd_rad, self.heading_baseline_m)

    def receive(self, stream_name: str, record) -> None:
        """A decoded record from stream ``stream_name`` (called on its reader thread): queued for
        the next ``advance``, and the service loop waiting in ``wait_for_input`` woken."""
        self.inbox.append((stream_name, record))
        self.input_arrived.set()

    def wait_for_input(self, timeout_s: float) -> bool:
        """Block until a record has arrived since the last call (True) or ``timeout_s`` has passed."""
        arrived = self.input_arrived.wait(max(timeout_s, 0.0))
        self.input_arrived.clear()      # what arrives from here on sets it again; the inbox keeps it
        return arrived

    def advance(self, t_gps_s: float) -> list[NavState]:
        self._drain()
        out = self.driver.run(now_s=t_gps_s)
        if out and math.isfinite(self._last_input_arrival_s):
            self.input_to_state_s.append(t_gps_s - self._last_input_arrival_s)
        return out

    def latency(self) -> dict:
        """Time from the arrival of the last input (host GPS time) to the ``advance`` call that
        returned the states it produced [ms]: median and 95th percentile over the last
        ``LATENCY_HISTORY`` advances that returned states."""
        x = np.asarray(self.input_to_state_s, float) * 1e3
        if not len(x):
            return {"input_to_state_ms_p50": None, "input_to_state_ms_p95": None, "n": 0}
        return {"input_to_state_ms_p50": float(np.median(x)), "input_to_state_ms_p95": float(np.percentile(x, 95)),
                "n": int(len(x))}

    @property
    def counts(self) -> dict:
        """What came in and what the driver did with it (``status()["counts"]``)."""
        d = self.driver.status()
        c, applied, fc = d["counts"], d["applied"], self.filter.counts
        return {**self._received, "gnss_used": applied["gnss"], "gnss_reordered": c["reordered"],
                "gnss_rejected_late": c["rejected_late"], "gnss_out_of_order": c["rejected_out_of_order"],
                "gnss_without_imu": c["applied_without_imu"], "imu_non_monotonic": c["imu_out_of_order"],
                "states": c["states"], "states_non_monotonic": c["states_non_monotonic"],
                "headings_used": fc.get("heading", 0) + fc.get("heading_sets", 0)}

    # ------------------------------------------------------------------ receiver
    def write_corrections(self, data: bytes) -> int:
        """Write RTCM3 bytes into the GNSS receiver's port (the same port it reports on)."""
        return self.gnss_stream.write(data)

    def status(self) -> dict:
        f = self.filter
        out = {"source": self.name, "counts": self.counts, "filter_counts": dict(f.counts),
               "initialized": bool(f.initialized), "pending": {**self.driver.pending(), "inbox": len(self.inbox)},
               "reorder_window_s": self.reorder_window_s, "latency": self.latency(),
               "imu_clock": self.imu_clock.status(),
               "streams": {"gnss": self.gnss_stream.stats()}}
        if self.imu_stream is not None:
            out["streams"]["imu"] = self.imu_stream.stats()
        g = self.last_gnss
        if g is not None:
            out["gnss"] = {"t_s": g.t_s, "fix": FixStatus(g.fix).name, "num_sv": g.num_sv, "message": g.message,
                           "sd_ned_m": [float(x) for x in g.sd_ned_m], "latency_s": g.arrival_s - g.t_s}
        h = self.last_heading
        if h is not None:
            out["heading"] = {"t_s": h.t_s, "heading_deg": math.degrees(h.heading_rad),
                              "sd_deg": math.degrees(h.heading_sd_rad), "baseline_m": h.baseline_m,
                              "message": h.message, "used_by_filter": self.heading_baseline_m is not None}
        if self.calibration is not None:
            out["calibration"] = {"source": self.calibration.source, "date": self.calibration.date,
                                  "effects": sorted(self.calibration.effects)}
        out["clock"] = self.clock.status()
        return out

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.gnss_stream.close()
        if self.imu_stream is not None:
            self.imu_stream.close()


def check_table(table: dict, where: str) -> dict:
    """Validate a ``device`` ``[source]`` table (``type`` removed) without opening anything; the
    parsed values. SourceError naming ``where`` and the key."""
    if not isinstance(table, dict):
        raise SourceError(f"{where}: expected a table")
    check_keys(table, SOURCE_KEYS, where, SourceError)
    if "gnss" not in table:
        raise SourceError(f"{where}.gnss: missing; e.g. gnss = {{ format = \"ubx\", port = \"/dev/ttyACM0\" }}")
    if "imu" not in table:
        raise SourceError(f"{where}.imu: missing; a stream table, or \"receiver\" for a receiver's ESF IMU")
    for key, how in REQUIRED_KEYS:
        if key not in table:
            raise SourceError(f"{where}.{key}: missing: {how}")
    platform = table["platform"]
    check_choice(platform, PLATFORMS, f"{where}.platform", SourceError)
    mounting = table["imu_to_body"]
    if isinstance(mounting, str):
        if mounting != "identity":
            raise SourceError(f"{where}.imu_to_body: {mounting!r}: a 3x3 rotation matrix, or \"identity\"")
        mounting = np.eye(3).tolist()
    imu_to_body = _matrix(mounting, (3, 3), f"{where}.imu_to_body")
    if not np.allclose(imu_to_body @ imu_to_body.T, np.eye(3), atol=1e-6) or np.linalg.det(imu_to_body) < 0:
        raise SourceError(f"{where}.imu_to_body: not a rotation matrix (orthonormal, determinant +1)")
    lever = _matrix(table["lever_arm_m"], (3,), f"{where}.lever_arm_m")
    lever_sd = table.get("lever_arm_sd_m", 0.1)
    window = table.get("reorder_window_s")
    span = table.get("imu_clock_min_span_s", 5.0)
    for key, v in (("lever_arm_sd_m", lever_sd), ("reorder_window_s", 0.0 if window is None else window),
                   ("imu_clock_min_span_s", span)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise SourceError(f"{where}.{key}: expected a number >= 0, got {v!r}")
    heading_baseline = None
    if "heading_baseline_m" in table:
        heading_baseline = _matrix(table["heading_baseline_m"], (3,), f"{where}.heading_baseline_m")
        if math.hypot(heading_baseline[0], heading_baseline[1]) == 0.0:
            raise SourceError(f"{where}.heading_baseline_m: a vertical baseline has no azimuth; "
                              f"got {heading_baseline.tolist()}")
    calibration = None
    if "calibration" in table:
        try:
            calibration = parse_calibration(table["calibration"], f"{where}.calibration")
        except CalibrationError as exc:
            raise SourceError(str(exc)) from None
    try:
        clock = clock_from_config(table.get("clock"), f"{where}.clock")
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    return {"platform": platform, "imu_to_body": imu_to_body, "lever": lever, "lever_sd": float(lever_sd),
            "window": None if window is None else float(window), "span": float(span), "calibration": calibration, "clock": clock,
            "heading_baseline": heading_baseline}


def from_config(table: dict, where: str, ctx: SourceContext) -> DeviceSource:
    """The ``device`` source from its ``[source]`` table (``type`` already removed); the ports are
    opened and their reader threads started. SourceError naming ``where`` and the key."""
    from v2xpos.ins.profiles import vehicle_config
    v = check_table(table, where)
    clock, calibration, window, span = v["clock"], v["calibration"], v["window"], v["span"]
    cfg = vehicle_config(v["platform"], v["imu_to_body"], v["lever"], v["lever_sd"], calibration,
                         **getattr(ctx, "filter_overrides", {}))

    holder: dict = {}

    def sink(name):
        return lambda rec: holder["source"].receive(name, rec)

    resolve = getattr(ctx, "resolve", lambda p: Path(p))
    try:
        gnss = open_stream(table["gnss"], "gnss", f"{where}.gnss", clock.host_gps_s, sink("gnss"), resolve)
        imu_t = table["imu"]
        if imu_t == "receiver":
            if gnss.format != "ubx":
                raise ValueError(f"{where}.imu: \"receiver\" needs a gnss stream of format \"ubx\" (ESF messages)")
            imu = None
        else:
            imu = open_stream(imu_t, "imu", f"{where}.imu", clock.host_gps_s, sink("imu"), resolve)
            if imu.format != "csv_g_dps_ms" and imu.format != "ubx":
                raise ValueError(f"{where}.imu.format: an IMU stream is \"csv_g_dps_ms\" or \"ubx\" (ESF)")
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    src = DeviceSource(gnss, imu, cfg, clock, reorder_window_s=window, imu_clock_min_span_s=float(span),
                       calibration=calibration, heading_baseline_m=v["heading_baseline"])
    holder["source"] = src
    src.start()
    return src
