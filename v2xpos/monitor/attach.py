"""Attach a ``MonitorState`` to a running master over zenoh, without adding work on the master.

It reads what every master already publishes: the status JSON (``v2xpos.wire.status_key``, at the
master's ``status_hz``) and the results republish (``v2xpos.wire.relative_key``, one message per
result when ``[output.zenoh] enabled``, the default), and once per target one of that target's own
state messages (``v2xpos.wire.state_key``) for its outline, after which that subscription is
undeclared.

Cost: the subscriptions use zenoh FIFO channels drained every ``drain_period_s`` by one thread -- no
Python callback per sample (a callback per sample costs the process clearly more CPU than the drain,
most of which is zenoh's own receive threads). Per sample the drain reads the target id from the
msgpack body and keeps the body; decoding with validation happens at refresh, once per target
(``MonitorState``).
"""
from __future__ import annotations

import json
import threading
import time
from typing import Callable

import msgpack
import zenoh

from v2xpos.link import Link, LinkConfig
from v2xpos.monitor.state import MonitorState
from v2xpos.wire import (MAX_MESSAGE_BYTES, VEHICLE_STATUS_KEY_ALL, WireError, decode_state, relative_key, state_key,
                         status_key)

FIFO_CAPACITY = 65536
GEOMETRY_RETRY_S = 10.0
GEOMETRY_MAX_PENDING = 4


class MasterMonitor:
    """``MonitorState`` fed from one master (``fleet``, ``master_id``) over ``link_cfg``.

    ``master_id=None``: the first master of the fleet whose status arrives (its id is then in
    ``master_id``); results of other masters are ignored.

    ``start()`` opens the zenoh session and the drain thread; every ``refresh_period_s`` the thread
    makes a new snapshot (``snapshot()`` returns the latest) and calls ``on_snapshot(snap)`` if
    given. ``close()`` stops the thread, undeclares everything and closes the session.
    """

    def __init__(self, link_cfg: LinkConfig, fleet: str, master_id: str | None, refresh_period_s: float = 0.2,
                 drain_period_s: float = 0.05, on_snapshot: Callable[[dict], None] | None = None,
                 trail_s: float = 20.0):
        self.link_cfg = link_cfg
        self.fleet = fleet
        self.master_id = master_id
        self.refresh_period_s = float(refresh_period_s)
        self.drain_period_s = float(drain_period_s)
        self.on_snapshot = on_snapshot
        self.state = MonitorState(trail_s=trail_s)
        self.link: Link | None = None
        self._lock = threading.Lock()
        self._snap: dict | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._geo_subs: dict[str, tuple[object, float]] = {}   # target -> (subscriber, declared at)
        self._geo_tried: dict[str, float] = {}
        self._auto = master_id is None
        self._rel_key = None if master_id is None else relative_key(fleet, master_id)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "MasterMonitor":
        self.link = Link(self.link_cfg)
        s = self.link.session
        self._rel = s.declare_subscriber(relative_key(self.fleet, self.master_id or "*"),
                                         zenoh.handlers.FifoChannel(FIFO_CAPACITY))
        self._status = s.declare_subscriber(status_key(self.fleet, self.master_id or "*"),
                                            zenoh.handlers.FifoChannel(64))
        self._vehicles = s.declare_subscriber(VEHICLE_STATUS_KEY_ALL(self.fleet), zenoh.handlers.FifoChannel(256))
        self._alive = s.liveliness().declare_subscriber(f"v2xpos/{self.fleet}/*/*/alive",
                                                       zenoh.handlers.FifoChannel(256), history=True)
        self._thread = threading.Thread(target=self._run, name="v2xpos-monitor", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self.link is not None:
            for sub, _ in self._geo_subs.values():
                _undeclare(sub)
            self._geo_subs.clear()
            _undeclare(self._rel)
            _undeclare(self._status)
            _undeclare(self._vehicles)
            _undeclare(self._alive)
            self.link.close()
            self.link = None

    def __enter__(self) -> "MasterMonitor":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def snapshot(self) -> dict | None:
        with self._lock:
            return self._snap

    # ------------------------------------------------------------------ drain thread
    def _run(self) -> None:
        next_refresh = time.monotonic()
        while not self._stop.is_set():
            self.drain()
            now = time.monotonic()
            if now >= next_refresh:
                next_refresh = now + self.refresh_period_s
                snap = self.refresh()
                if self.on_snapshot is not None:
                    self.on_snapshot(snap)
            self._stop.wait(self.drain_period_s)

    def drain(self) -> int:
        """Take everything queued (results, status, outlines); returns the number of results."""
        st = self.state
        n = 0
        t_wall = time.time()
        try_recv = self._rel.try_recv
        while True:
            try:
                sample = try_recv()
            except Exception:   # session closing
                break
            if sample is None:
                break
            n += 1
            if self._auto and (self.master_id is None or str(sample.key_expr) != self._rel_key):
                continue
            body, tid = _body_and_target(sample.payload.to_bytes())
            if body is None:
                st.received += 1
                st.malformed += 1
                continue
            st.on_relative(body, tid, t_wall)
        for sample in _drain(self._status):
            if self._auto:
                key = str(sample.key_expr)
                if self.master_id is None:
                    self.master_id = key.split("/")[3]
                    self._rel_key = relative_key(self.fleet, self.master_id)
                elif key != status_key(self.fleet, self.master_id):
                    continue
            doc = _json_map(sample)
            if doc is not None:
                st.on_status(doc, t_wall)
        for sample in _drain(self._vehicles):
            doc = _json_map(sample)
            if doc is not None:
                st.on_vehicle_status(doc, t_wall)
        for sample in _drain(self._alive):
            parts = str(sample.key_expr).split("/")    # v2xpos/<fleet>/<role>/<id>/alive
            if len(parts) == 5:
                st.on_alive(parts[2], parts[3], sample.kind == zenoh.SampleKind.PUT, t_wall)
        self._outlines(t_wall)
        return n

    def refresh(self) -> dict:
        snap = self.state.refresh(time.time())
        with self._lock:
            self._snap = snap
        return snap

    def _outlines(self, t_wall: float) -> None:
        """One state message per target for its outline (subscribe, take one, undeclare)."""
        for tid, (sub, t0) in list(self._geo_subs.items()):
            got = None
            try:
                while (sample := sub.try_recv()) is not None:
                    got = sample
            except Exception:
                pass
            if got is not None:
                try:
                    self.state.on_geometry(tid, decode_state(got.payload.to_bytes()).geometry)
                except WireError:
                    got = None
            if got is not None or t_wall - t0 > GEOMETRY_RETRY_S:
                _undeclare(sub)
                del self._geo_subs[tid]
        for tid in self.state.targets():
            if len(self._geo_subs) >= GEOMETRY_MAX_PENDING:
                break
            if (self.state.has_geometry(tid) or tid in self._geo_subs
                    or t_wall - self._geo_tried.get(tid, -1e18) < GEOMETRY_RETRY_S):
                continue
            self._geo_tried[tid] = t_wall
            try:
                sub = self.link.session.declare_subscriber(state_key(self.fleet, tid), zenoh.handlers.FifoChannel(4))
            except Exception:   # an id that is not a valid key expression
                continue
            self._geo_subs[tid] = (sub, t_wall)


def _json_map(sample) -> dict | None:
    """A sample's JSON object payload, or None when it is not one."""
    try:
        doc = json.loads(sample.payload.to_bytes())
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def _drain(sub) -> list:
    """Everything queued on a FIFO subscriber (nothing once its session closes)."""
    out = []
    while True:
        try:
            sample = sub.try_recv()
        except Exception:   # session closing
            return out
        if sample is None:
            return out
        out.append(sample)


def _undeclare(sub) -> None:
    try:
        sub.undeclare()
    except Exception:   # already gone with its session
        pass


def _body_and_target(payload: bytes) -> tuple[bytes | None, str | None]:
    """The body of a RelativeResult envelope and its target id, or (None, None) if malformed.
    Only the structure needed to route it is checked here; ``decode_relative_body`` validates the
    body at refresh."""
    if len(payload) > MAX_MESSAGE_BYTES:
        return None, None
    try:
        env = msgpack.unpackb(payload, raw=False)
        body = env[1]
        tid = msgpack.unpackb(body, raw=False).get("target")
    except Exception:   # any msgpack/shape error: not a result
        return None, None
    if type(body) is not bytes or type(tid) is not str:
        return None, None
    return body, tid
