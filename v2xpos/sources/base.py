"""One interface for every place a vehicle's state can come from, and for the clock it runs on.

A service (``master/``, ``slave/``) holds one :class:`VehicleSource` and one
:class:`SessionClock` and never knows which kind they are:

* ``recording`` (``v2xpos.sources.recording``): a ``dataset.toml`` replayed on its own GPS time;
* ``device`` (``v2xpos.sources.device``): live receivers and IMUs over serial ports or TCP,
  stamped on arrival by the host clock, on GPS time from the host clock;
* ``sim``: the simulator, registered by ``sim/`` under the entry-point group ``v2xpos.sources``
  (the library never imports it).

Time: every ``t_gps_s`` is GPS seconds since 1980-01-06 (``v2xpos.timebase``). ``advance(t)``
consumes every sensor sample whose time of validity is <= t and returns the navigation states
produced, oldest first; a service calls it with ``clock.now_gps_s()``.
"""
from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from v2xpos.types import NavState


class SourceError(ValueError):
    """A source that cannot be built or read; the message names the file/device and the key."""


@dataclass
class SourceContext:
    """What a source factory may need from the service that owns it.

    vehicle_id / fleet: identity of the vehicle; role: "master" or "slave"; config_dir: directory of
    the config file (relative paths in ``[source]`` are resolved against it); link: the service's
    ``v2xpos.link.Link`` once open (sources that synchronise over the network use it); stop:
    returns True when the service is asked to stop (long waits poll it); filter_overrides:
    ``InsConfig`` groups (each a dict of some of its fields) the service's configuration sets for
    the vehicle's filter (its ``[validity]`` alert limit and integrity risk in ``integrity``,
    ``v2xpos.config.validity_from_table``).
    """
    vehicle_id: str
    fleet: str = "demo"
    role: str = "slave"
    config_dir: Path = field(default_factory=Path.cwd)
    link: Any = None
    stop: Callable[[], bool] = lambda: False
    extra: dict = field(default_factory=dict)
    filter_overrides: dict = field(default_factory=dict)

    def resolve(self, path: str) -> Path:
        """``path`` relative to the config file's directory (absolute paths unchanged)."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else (self.config_dir / p)


class SessionClock(ABC):
    """The time a service runs on (GPS seconds), and how it maps to the host's wall clock.

    ``now_gps_s()`` is the session time; ``wall_of(t)`` the ``time.time()`` at which the session
    reaches ``t`` (for sleeping); ``start()`` blocks until the session time begins (a recording
    waiting for its peers, a simulation waiting for its start stamp) and returns False if stopped
    first. ``status()`` is a JSON-ready dict for the service status; ``synchronised()`` says
    whether results may be VALID as far as time is concerned.
    """

    speed: float = 1.0
    t_start_gps_s: float | None = None
    """Where the session's own time starts (a scenario epoch, a recording's first sample); a
    service's ``duration_s`` counts from here. None: from the moment ``start()`` returns."""

    @abstractmethod
    def now_gps_s(self) -> float: ...

    def session_start_gps_s(self) -> float:
        """``t_start_gps_s`` when the clock defines one, else the time now (call after ``start``)."""
        return self.now_gps_s() if self.t_start_gps_s is None else float(self.t_start_gps_s)

    def wall_of(self, t_gps_s: float) -> float:
        """Host wall time [Unix s] at which the session reaches ``t_gps_s``."""
        return time.time() + (t_gps_s - self.now_gps_s()) / self.speed

    def start(self, stop: Callable[[], bool] = lambda: False) -> bool:
        """Block until the session time runs; False if ``stop()`` became true first."""
        return not stop()

    def synchronised(self) -> bool:
        """True while this clock is good enough for VALID results."""
        return True

    def status(self) -> dict:
        return {"kind": type(self).__name__}

    def close(self) -> None:
        """Release what ``start`` opened (network subscriptions)."""


class VehicleSource(ABC):
    """A vehicle's navigation states as time advances (see the module docstring).

    Attributes: ``name`` (the source type: recording, device, sim), ``kind`` ("vehicle" or
    "pedestrian"), ``geometry`` (``v2xpos.wire.Geometry`` outline in the body frame, or None for
    the default box).
    """

    name: str = "source"
    kind: str = "vehicle"
    geometry: Any = None

    @abstractmethod
    def advance(self, t_gps_s: float) -> list[NavState]:
        """Consume every input with time of validity <= ``t_gps_s``; the states produced, in order."""

    @abstractmethod
    def make_clock(self, ctx: SourceContext) -> SessionClock:
        """The session clock that suits this source (recording time, host GNSS time, scenario)."""

    def warm_up(self) -> None:
        """Work that must happen before real time starts (JIT compilation, loading)."""

    def prime(self, t_gps_s: float) -> NavState | None:
        """Run the filter through the history before the session starts (up to ``t_gps_s``) and
        return the last state, without publishing it. Default: ``advance``."""
        states = self.advance(t_gps_s)
        return states[-1] if states else None

    def wait_for_input(self, timeout_s: float) -> bool:
        """Block until new input has arrived (True) or ``timeout_s`` has passed (False). A service
        loop waits here between its ticks, so that a source fed by devices is advanced as soon as
        a record arrives instead of at the next tick. Default (inputs that are not pushed: a
        recording, a simulation): sleep ``timeout_s``."""
        if timeout_s > 0:
            time.sleep(timeout_s)
        return False

    def status(self) -> dict:
        """JSON-ready status: counters, receiver/clock figures, correction stream."""
        return {"source": self.name}

    def finished(self, t_gps_s: float) -> bool:
        """True when no input remains after ``t_gps_s`` (end of a recording); live sources never finish."""
        return False

    def write_corrections(self, data: bytes) -> int:
        """Write RTCM3 correction bytes into the receiver; bytes written (0: no receiver)."""
        return 0

    def imu_units(self) -> tuple[dict, dict] | None:
        """``({unit_id: ImuData}, {unit_id: mounting X-Y-Z deg})`` of every IMU on board for live
        grading, or None when the source has a single unit."""
        return None

    def close(self) -> None:
        """Stop reader threads, close ports."""


class Stopped(Exception):
    """A blocking start-up step was abandoned because the service was asked to stop."""


def run_until_stopped(fn: Callable[..., Any], stop: Callable[[], bool], *args: Any, poll_s: float = 0.05) -> Any:
    """Run a blocking step (loading a recording, JIT warm-up, waiting for a clock) on a daemon thread
    and return its result, or raise :class:`Stopped` within ``poll_s`` of ``stop()`` turning true
    (the thread is abandoned: a daemon thread does not hold the process at exit). Exceptions of
    ``fn`` are re-raised in the caller."""
    box: dict = {}
    done = threading.Event()

    def work() -> None:
        try:
            box["result"] = fn(*args)
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the caller
            box["error"] = exc
        finally:
            done.set()

    threading.Thread(target=work, name=f"v2xpos-{getattr(fn, '__name__', 'step')}", daemon=True).start()
    while not done.wait(poll_s):
        if stop():
            raise Stopped
    if "error" in box:
        raise box["error"]
    return box.get("result")
