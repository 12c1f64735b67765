"""The session clock of recordings: each recording runs on its own GPS time.

A recording is replayed on the GPS time it was recorded at, paced by the host's monotonic clock:
``t_gps = t0 + speed * (wall - w0)``. No epoch, no shift: two recordings of the same drive (two
cars) have the same GPS time, so the master and its slaves agree on time if they agree on the
anchor ``(t0, w0)``. That agreement is the only thing they exchange, over the service's own zenoh
link (the idea of ROS's ``/clock`` topic for simulated time):

* the master's clock is the **leader**: it waits until the vehicles named in ``wait_for`` say they
  are ready (``v2xpos/<fleet>/session/ready/<id>``), starts at its recording's first sample and
  publishes ``{t_gps_s, speed, leader}`` on ``v2xpos/<fleet>/session/clock`` every
  ``CLOCK_PERIOD_S``;
* a slave's clock is a **follower**: it announces itself ready, then anchors on the leader's
  messages. A message that took ``d`` seconds to arrive says ``t_msg = t_true(w_recv) - speed * d``,
  so the offset ``t_msg - speed * w_recv`` underestimates the true one by ``speed * d >= 0``;
  keeping the largest value seen converges on the fastest message (the lower-envelope idea of
  ``v2xpos.timebase``);
* ``alone`` starts at once on the recording's own first sample (a single service).

``time.time()`` is used for the anchor because the leader and its followers on one host must
share it; a recording is not a live vehicle, so no GNSS discipline is assumed.
"""
from __future__ import annotations

import json
import threading
import time
from typing import Any, Callable

from v2xpos.wire import clock_key, ready_key

from .base import SessionClock

CLOCK_PERIOD_S = 0.1
READY_PERIOD_S = 0.2
START_LEAD_S = 0.3
"""The leader anchors its first sample this long after everyone is ready, so that followers
have its clock before the first state is due."""
MODES = ("leader", "follower", "alone")


class ReplayClock(SessionClock):
    """Recording GPS time paced by the host clock (see the module docstring).

    t_begin_gps_s: the recording's first sample (where ``leader``/``alone`` start); speed: session
    seconds per wall second; mode: leader | follower | alone; link: the service's
    ``v2xpos.link.Link`` (leader and follower); wait_for: ids the leader waits for;
    wait_timeout_s: how long a leader waits for them (then starts and says who is missing) and how
    long a follower waits for the leader (then fails).
    """

    def __init__(self, t_begin_gps_s: float, speed: float = 1.0, mode: str = "alone", link: Any = None,
                 fleet: str = "demo", vehicle_id: str = "", wait_for: tuple = (), wait_timeout_s: float = 120.0,
                 say: Callable[[str], None] = print):
        if mode not in MODES:
            raise ValueError(f"clock mode {mode!r} is not one of {MODES}")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        if mode != "alone" and link is None:
            raise ValueError(f"a {mode} clock needs the service's link")
        self.t_begin_gps_s = float(t_begin_gps_s)
        self.t_start_gps_s = self.t_begin_gps_s if mode != "follower" else None
        self.speed = float(speed)
        self.mode = mode
        self.link = link
        self.fleet = fleet
        self.vehicle_id = vehicle_id
        self.wait_for = tuple(wait_for)
        self.wait_timeout_s = float(wait_timeout_s)
        self.say = say
        self._offset_s: float | None = None          # t_gps = offset + speed * time.time()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._ready: set[str] = set()
        self.leader_id: str | None = None
        self.clock_messages = 0
        self.missing: list[str] = []

    # ---- time
    def now_gps_s(self) -> float:
        off = self._offset_s
        if off is None:
            return self.t_begin_gps_s - 1e-3
        return off + self.speed * time.time()

    def wall_of(self, t_gps_s: float) -> float:
        off = self._offset_s
        if off is None:
            return time.time() + 0.01
        return (t_gps_s - off) / self.speed

    def _anchor(self, t_gps_s: float, wall_s: float) -> None:
        self._offset_s = t_gps_s - self.speed * wall_s

    # ---- start
    def start(self, stop: Callable[[], bool] = lambda: False) -> bool:
        if self.mode == "alone":
            self._anchor(self.t_begin_gps_s, time.time())
            return not stop()
        if self.mode == "leader":
            return self._start_leader(stop)
        return self._start_follower(stop)

    def _start_leader(self, stop: Callable[[], bool]) -> bool:
        prefix = ready_key(self.fleet, "")      # the vehicle id follows

        def on_ready(payload: bytes, key: str, att: Any, t_arr: float) -> None:
            with self._lock:
                self._ready.add(key[len(prefix):])

        self.link.subscribe(ready_key(self.fleet, "*"), on_ready)
        t_end = time.monotonic() + self.wait_timeout_s
        said = False
        while not stop():
            with self._lock:
                missing = [v for v in self.wait_for if v not in self._ready]
            if not missing:
                break
            if time.monotonic() > t_end:
                self.missing = missing
                self.say(f"session clock: starting without {missing} (not ready after {self.wait_timeout_s:.0f} s)")
                break
            if not said:
                self.say(f"session clock: waiting for {missing} to be ready")
                said = True
            time.sleep(0.02)
        if stop():
            return False
        self._anchor(self.t_begin_gps_s, time.time() + START_LEAD_S / self.speed)
        pub = self.link.publisher(clock_key(self.fleet), express=True)

        def publish() -> None:
            while not self._stop.is_set():
                doc = {"t_gps_s": self.now_gps_s(), "speed": self.speed, "leader": self.vehicle_id}
                try:
                    pub.put(json.dumps(doc).encode())
                except Exception:   # session closing
                    return
                self._stop.wait(CLOCK_PERIOD_S)

        self._spawn(publish, "v2xpos-clock-leader")
        return True

    def _on_clock(self, payload: bytes, key: str, att: Any, t_arr: float) -> None:
        try:
            doc = json.loads(payload)
            t = float(doc["t_gps_s"])
            speed = float(doc["speed"])
        except (ValueError, KeyError, TypeError):
            return
        with self._lock:
            self.clock_messages += 1
            self.leader_id = str(doc.get("leader", ""))
            if speed > 0 and speed != self.speed:
                self.speed = speed
                self._offset_s = None
            off = t - self.speed * t_arr
            if self._offset_s is None or off > self._offset_s:
                self._offset_s = off

    def _start_follower(self, stop: Callable[[], bool]) -> bool:
        self.link.subscribe(clock_key(self.fleet), self._on_clock)
        pub = self.link.publisher(ready_key(self.fleet, self.vehicle_id), express=True)

        def announce() -> None:
            while not self._stop.is_set():
                try:
                    pub.put(b"ready")
                except Exception:
                    return
                self._stop.wait(READY_PERIOD_S)

        self._spawn(announce, "v2xpos-clock-ready")
        t_end = time.monotonic() + self.wait_timeout_s
        said = False
        while self._offset_s is None:
            if stop():
                return False
            if time.monotonic() > t_end:
                raise TimeoutError(f"no session clock on {clock_key(self.fleet)} after {self.wait_timeout_s:.0f} s "
                                   "(is the master running on its recording?)")
            if not said:
                self.say(f"waiting for the session clock on {clock_key(self.fleet)}")
                said = True
            time.sleep(0.02)
        return not stop()

    def _spawn(self, target: Callable[[], None], name: str) -> None:
        th = threading.Thread(target=target, name=name, daemon=True)
        th.start()
        self._threads.append(th)

    # ---- status
    def missing(self) -> list[str]:
        """The vehicles a leader still waits for (empty once the session runs, or for a follower)."""
        return [v for v in self.wait_for if v not in self._ready] if self.mode == "leader" else []

    def status(self) -> dict:
        return {"kind": "recording", "mode": self.mode, "speed": self.speed, "t_gps_s": self.now_gps_s(),
                "started": self._offset_s is not None, "leader": self.leader_id,
                "clock_messages": self.clock_messages, "missing": self.missing}

    def close(self) -> None:
        self._stop.set()
        for th in self._threads:
            th.join(timeout=1.0)
