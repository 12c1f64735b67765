"""The ``recording`` source: a recorded drive (``dataset.toml``) replayed on its own GPS time.

``[source]`` table::

    type = "recording"
    dataset = "../shared/data/convoy_dev/B/dataset.toml"   # relative to the config file
    speed = 1.0          # session seconds per wall second (> 1: faster than real time)
    sync = "auto"        # auto: a master leads the session clock, a slave follows it; none: alone
    wait_for = ["B"]     # leader only: vehicles to wait for before the clock starts
    wait_timeout_s = 120
    outline_m = [3.8, 1.0, 0.9]   # optional: front, rear, half width of the body outline [m]

The recording goes through the navigation filter (``v2xpos.ins.InsFilter``) on the one driver
(``v2xpos.ins.driver.InsDriver``) exactly as in ``v2xpos replay`` without outages -- the same
events (IMU samples, GNSS epochs, wheel speeds), the same order, the same filter profile (the
services' one, ``v2xpos.ins.profiles``) -- so the states are identical: ``advance(t)`` processes
every event whose time of validity is <= t and returns one NavState per IMU sample once the filter
is initialised, stamped with the time it is valid for (the IMU stamp from the recording's clock
model plus the filter's IMU time-offset estimate). Times are the recording's own GPS times;
nothing is shifted onto another epoch.
"""
from __future__ import annotations

import sys
from pathlib import Path

from v2xpos.schema import Key, check_choice, read_table
from v2xpos.types import NavState

from .base import SessionClock, SourceContext, SourceError, VehicleSource
from .clock import ReplayClock


SCHEMA = (Key("dataset", str, None), Key("speed", float, 1.0, above=0.0, high=1000.0), Key("sync", str, "auto"),
          Key("wait_for", list, []), Key("wait_timeout_s", float, 120.0, above=0.0, high=86400.0),
          Key("outline_m", list, None))
"""The ``recording`` ``[source]`` table (without ``type``)."""


def check_table(table: dict, where: str) -> dict:
    """Validate a ``recording`` ``[source]`` table (without ``type``) without loading anything; the
    parsed values. SourceError naming ``where`` and the key."""
    t = read_table(table, SCHEMA, where, SourceError)
    path, speed, sync, wait_for, timeout, outline = t.values()
    if not path:
        raise SourceError(f"{where}.dataset: required: the recording's dataset.toml (or its folder)")
    check_choice(sync, ("auto", "none"), f"{where}.sync", SourceError)
    if not all(isinstance(x, str) for x in wait_for):
        raise SourceError(f"{where}.wait_for: expected a list of vehicle ids")
    if outline is not None and (not isinstance(outline, list) or len(outline) != 3
                                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and x >= 0
                                           for x in outline)):
        raise SourceError(f"{where}.outline_m: expected [front, rear, half_width] in metres (>= 0)")
    return {"dataset": path, "speed": speed, "sync": sync, "wait_for": tuple(wait_for), "wait_timeout_s": timeout,
            "outline_m": outline}


DECLARED = (("imu", "imu_to_body"), ("gnss", "lever_arm_m"))
"""What a recording a vehicle service runs on must declare in its descriptor (the loader's defaults,
identity and zero, are for analysing a recording, not for a vehicle's reference)."""


def check_declared(path, where: str) -> None:
    """SourceError naming the descriptor, the table and the key when the recording does not declare
    its IMU mounting or its antenna lever arm."""
    from v2xpos.datasets.loader import read_descriptor
    path = Path(path) / "dataset.toml" if Path(path).is_dir() else Path(path)
    try:
        desc = read_descriptor(path)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{where}.dataset: {exc}") from None
    for table, key in DECLARED:
        if key not in (desc.get(table) or {}):
            raise SourceError(f"{where}.dataset: {path}: [{table}] {key} missing: declare it (the identity "
                              f"mounting as [[1, 0, 0], [0, 1, 0], [0, 0, 1]], a coincident antenna as [0, 0, 0])")


def from_config(table: dict, where: str, ctx: SourceContext) -> "RecordingSource":
    """Build from a ``[source]`` table (without ``type``); errors name ``where`` and the key."""
    v = check_table(table, where)
    path = ctx.resolve(v.pop("dataset"))
    check_declared(path, where)
    try:
        return RecordingSource(path, **v, filter_overrides=getattr(ctx, "filter_overrides", None))
    except (OSError, ValueError) as exc:
        raise SourceError(f"{where}.dataset: {exc}") from None


def ins_config_for(ds, **overrides) -> "object":
    """The filter configuration of a recording: its declared mounting and lever arm, the platform's
    vehicle constraints, its ``[calibration]`` table and its wheel speeds, in the services'
    profile (``v2xpos.ins.profiles.dataset_config``: the same function ``v2xpos replay`` and the
    device source use, so a vehicle is the same filter everywhere); ``overrides``: ``InsConfig``
    groups the service sets (its ``[validity]`` in ``integrity``)."""
    from v2xpos.ins.profiles import dataset_config
    return dataset_config(ds, **overrides)


class RecordingSource(VehicleSource):
    """A recorded drive through the INS filter on its own GPS time (see the module docstring)."""

    name = "recording"

    def __init__(self, path: str | Path, speed: float = 1.0, sync: str = "auto", wait_for: tuple = (),
                 wait_timeout_s: float = 120.0, outline_m: list | None = None, filter_overrides: dict | None = None):
        from v2xpos.datasets.loader import load_dataset
        from v2xpos.ins import InsFilter
        from v2xpos.ins.driver import InsDriver, push_dataset
        from v2xpos.wire import Geometry
        self.path = Path(path)
        self.ds = load_dataset(path)
        if len(self.ds.imu) == 0 or len(self.ds.gnss) == 0:
            raise ValueError(f"{path}: the recording has no IMU samples or no GNSS epochs")
        self.speed = speed
        self.sync = sync
        self.wait_for = wait_for
        self.wait_timeout_s = wait_timeout_s
        self.kind = "pedestrian" if self.ds.platform == "pedestrian" else "vehicle"
        if outline_m is not None:
            self.geometry = Geometry.box(*(float(x) for x in outline_m))
        elif self.kind == "pedestrian":
            self.geometry = Geometry(kind="circle", radius_m=0.3)
        else:
            self.geometry = Geometry.box(3.8, 1.0, 0.9)
        self.filter = InsFilter(ins_config_for(self.ds, **(filter_overrides or {})))
        self.driver = InsDriver(self.filter, complete=True, emit_states=True)
        push_dataset(self.driver, self.ds)

    @property
    def t_begin_gps_s(self) -> float:
        return float(self.ds.imu.t_s[0])

    @property
    def t_end_gps_s(self) -> float:
        return float(self.ds.imu.t_s[-1])

    def make_clock(self, ctx: SourceContext) -> SessionClock:
        mode = "alone" if self.sync == "none" else ("leader" if ctx.role == "master" else "follower")
        return ReplayClock(self.t_begin_gps_s, speed=self.speed, mode=mode, link=ctx.link, fleet=ctx.fleet,
                           vehicle_id=ctx.vehicle_id, wait_for=self.wait_for, wait_timeout_s=self.wait_timeout_s,
                           say=lambda m: print(f"{ctx.role} {ctx.vehicle_id}: {m}", file=sys.stderr, flush=True))

    def warm_up(self) -> None:
        """Compile the filter's kernels (or load their cache) before the session's time runs."""
        from v2xpos.ins.driver import warm_up
        warm_up(self.filter.cfg)

    def advance(self, t_gps_s: float) -> list[NavState]:
        return self.driver.run(until_s=t_gps_s)

    def finished(self, t_gps_s: float) -> bool:
        return self.driver.done()

    def status(self) -> dict:
        d = self.driver.status()
        return {"source": self.name, "dataset": str(self.path), "name": self.ds.name,
                "span_gps_s": [self.t_begin_gps_s, self.t_end_gps_s],
                "imu_done": len(self.ds.imu) - d["pending"]["imu"], "imu_samples": len(self.ds.imu),
                "gnss_updates": d["applied"]["gnss"], "non_monotonic": d["counts"]["states_non_monotonic"],
                "driver": d["counts"], "malformed_lines": self.ds.malformed_lines}
