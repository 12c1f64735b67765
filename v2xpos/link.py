"""Zenoh link for the V2V services: loopback-safe configuration, key expressions, publisher and an
asyncio subscriber bridge.

Configuration (zenoh 1.x JSON5 keys, see the zenoh ``DEFAULT_CONFIG.json5``):

* ``mode``: ``router`` (the master embeds the router by default), ``peer`` or ``client``;
* ``listen/endpoints`` and ``connect/endpoints``: explicit ``tcp/127.0.0.1:PORT`` locators only
  by default -- nothing binds a wildcard address and nothing leaves the machine;
* ``scouting/multicast/enabled = false`` and ``scouting/gossip/enabled = false``: no discovery
  traffic at all, peers only know the endpoints they are given;
* ``connect/retry``: reconnection period starts at ``retry_init_ms`` (default 100 ms), grows by
  ``retry_factor`` up to ``retry_max_ms`` (default 500 ms), so a client whose router restarts
  resumes delivery within about half a second; ``exit_on_failure = false``: a ``peer`` opens at
  once and connects in the background when its router comes up; a ``client`` cannot open without
  a reachable router, so ``connect_timeout_ms`` says how long ``zenoh.open`` waits for one (-1:
  forever).
* Topology: a router forwards client <-> client, client <-> peer and its own traffic, but with
  scouting off it does NOT forward between two peers that are both connected to it (zenoh expects
  peers to mesh directly). Slaves, monitors and the grading worker are therefore ``client``s of the
  master's router; ``peer`` is for a master that joins a standalone router mesh.

Key expressions live in ``v2xpos.wire``.

Threading: zenoh calls subscriber callbacks on its own threads. ``AsyncSubscriber`` hands each
sample over to an asyncio loop with ``loop.call_soon_threadsafe`` (the only thread-safe entry
into a loop), stamping the arrival wall time on the zenoh thread so queueing in the loop counts
as pipeline latency. ``Link.close()`` undeclares every entity it created, then closes the session
(deterministic shutdown, no reliance on garbage collection).
"""
from __future__ import annotations

import asyncio
import json
import math
import re
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import zenoh

MODES = ("router", "peer", "client")


class LinkError(OSError):
    """The zenoh session could not be opened; the message names the mode and the endpoints
    (an OSError: the port, the router or the network is the problem, not the program)."""


def _zenoh_reason(exc: BaseException) -> str:
    """zenoh's error text without its Rust source locations (`` at /path/file.rs:61.``)."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc))
    return " ".join(text.replace("[", "").replace("]", "").split()).rstrip(".")


def open_error(config: "LinkConfig", exc: BaseException) -> LinkError:
    """A one-line LinkError for a failed ``zenoh.open`` with ``config``."""
    reason = _zenoh_reason(exc)
    where = []
    if config.listen:
        where.append(f"listening on {', '.join(config.listen)}")
    if config.connect:
        where.append(f"connecting to {', '.join(config.connect)}")
    hint = ""
    if "already in use" in reason.lower():
        hint = " (another master or router already uses that port: stop it or choose another port)"
    elif config.mode == "client" and config.connect:
        hint = " (is the master's router running? see connect_timeout_ms)"
    return LinkError(f"zenoh {config.mode} cannot open ({' and '.join(where) or 'no endpoints'}): "
                     f"{reason}{hint}")


def loopback_endpoint(port: int, host: str = "127.0.0.1") -> str:
    """``tcp/HOST:PORT`` locator (loopback by default)."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} out of range 1..65535")
    return f"tcp/{host}:{int(port)}"


@dataclass
class LinkConfig:
    """Zenoh session settings of one service.

    mode: router | peer | client. listen / connect: explicit locators (``tcp/127.0.0.1:PORT``).
    retry_*: reconnection back-off [ms]. connect_timeout_ms: zenoh ``connect/timeout_ms`` (None =
    zenoh default; -1 = wait forever). extra_json5: further ``key -> JSON value`` insertions
    applied last (e.g. TLS ``transport/link/tls/...``), for options this class does not name.
    """
    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    retry_init_ms: int = 100
    retry_max_ms: int = 500
    retry_factor: float = 1.5
    connect_timeout_ms: int | None = None
    extra_json5: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"link mode {self.mode!r} is not one of {MODES}")
        for ep in [*self.listen, *self.connect]:
            if not isinstance(ep, str) or "/" not in ep:
                raise ValueError(f"link endpoint {ep!r} is not a locator like 'tcp/127.0.0.1:7447'")

    @classmethod
    def from_dict(cls, d: dict, where: str = "[link]") -> "LinkConfig":
        """Build from a TOML/JSON table; unknown keys are rejected with their location."""
        from v2xpos.schema import field_key, read_table
        kw = read_table(d, (field_key(cls, "mode", str), field_key(cls, "listen", (list, str)),
                            field_key(cls, "connect", (list, str)), field_key(cls, "retry_init_ms", int, low=1),
                            field_key(cls, "retry_max_ms", int, low=1), field_key(cls, "retry_factor", float, low=1),
                            field_key(cls, "connect_timeout_ms", int, low=-1), field_key(cls, "extra_json5", dict)),
                        where)
        for k in ("listen", "connect"):
            if isinstance(kw[k], str):
                kw[k] = [kw[k]]
        try:
            return cls(**kw)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None

    def to_zenoh(self) -> zenoh.Config:
        """The zenoh.Config these settings describe."""
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("scouting/gossip/enabled", "false")
        c.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        c.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.connect_timeout_ms is not None:
            c.insert_json5("connect/timeout_ms", str(int(self.connect_timeout_ms)))
        c.insert_json5("connect/exit_on_failure", "false")
        retry = {"period_init_ms": int(self.retry_init_ms), "period_max_ms": int(self.retry_max_ms),
                 "period_increase_factor": float(self.retry_factor)}
        c.insert_json5("connect/retry", json.dumps(retry))
        for key, value in self.extra_json5.items():
            c.insert_json5(key, json.dumps(value))
        return c


LinkUnavailable = LinkError
"""The name the services use for a session that could not be opened."""


class Link:
    """One zenoh session plus the publishers and subscribers declared through it."""

    def __init__(self, config: LinkConfig):
        self.config = config
        try:
            self.session = zenoh.open(config.to_zenoh())
        except zenoh.ZError as exc:
            raise open_error(config, exc) from None
        self._entities: list[Any] = []
        self._closed = False

    @classmethod
    def open_when_available(cls, config: LinkConfig, stop: Callable[[], bool] = lambda: False,
                            say: Callable[[str], None] = print, attempt_ms: int = 500) -> "Link | None":
        """Open the session; a client whose router is not up yet says so once and retries every
        ``attempt_ms`` until it connects or ``stop()`` (None then). Each attempt blocks at most
        ``attempt_ms`` inside ``zenoh.open`` (which does not return to Python for signals), so a
        SIGINT/SIGTERM handler that sets the stop flag is honoured within about that time.
        A router or peer opens at once (peers connect in the background); their errors (address in
        use) raise ``LinkUnavailable`` at once."""
        if config.mode != "client":
            return cls(config)
        budget_ms = config.connect_timeout_ms
        t_end = math.inf if budget_ms is None or budget_ms < 0 else time.monotonic() + budget_ms / 1e3
        attempt = LinkConfig(**{**config.__dict__, "connect_timeout_ms": int(attempt_ms)})
        said = False
        while not stop():
            try:
                link = cls(attempt)
                link.config = config
                if said:
                    say(f"connected to {', '.join(config.connect)}")
                return link
            except LinkUnavailable as exc:
                if time.monotonic() >= t_end:
                    raise LinkUnavailable(f"{exc} (gave up after {budget_ms} ms)") from None
                if not said:
                    say(f"waiting for the zenoh router at {', '.join(config.connect) or '?'} (retrying; Ctrl-C stops)")
                    said = True
        return None

    def publisher(self, key: str, block: bool = True, express: bool = True) -> "Publisher":
        """Publisher on ``key``; ``block`` selects CongestionControl.BLOCK (nothing dropped on a
        full queue), ``express`` sends without batching (lowest latency)."""
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self.session.declare_publisher(key, congestion_control=cc, express=express)
        self._entities.append(pub)
        return Publisher(pub)

    def declare_alive(self, key: str):
        """Declare a liveliness token on ``key`` (``v2xpos.wire.alive_key``): peers see it go when
        this session closes, also when the process is killed (zenoh liveliness)."""
        token = self.session.liveliness().declare_token(key)
        self._entities.append(token)
        return token

    def subscribe(self, key: str, callback: Callable[[bytes, str, bytes | None, float], None]):
        """Subscribe with a plain callback ``cb(payload, key, attachment, arrival_wall_s)`` called on
        a zenoh thread."""
        def on_sample(sample: zenoh.Sample) -> None:
            t_arr = time.time()
            att = sample.attachment
            callback(sample.payload.to_bytes(), str(sample.key_expr),
                     None if att is None else att.to_bytes(), t_arr)
        sub = self.session.declare_subscriber(key, on_sample)
        self._entities.append(sub)
        return sub

    def subscribe_async(self, key: str, loop: asyncio.AbstractEventLoop | None = None,
                        maxsize: int = 0) -> "AsyncSubscriber":
        """Subscription whose samples arrive in an asyncio.Queue of ``Received`` (see AsyncSubscriber)."""
        return AsyncSubscriber(self, key, loop or asyncio.get_running_loop(), maxsize)

    def close(self) -> None:
        """Undeclare everything, then close the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for ent in reversed(self._entities):
            try:
                ent.undeclare()
            except Exception:  # already undeclared by the session; nothing left to release
                pass
        self._entities.clear()
        self.session.close()

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Publisher:
    """Thin wrapper: ``put(payload, attachment=None)``; counts what it sent."""

    def __init__(self, pub: zenoh.Publisher):
        self._pub = pub
        self.sent = 0

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        if attachment is None:
            self._pub.put(payload)
        else:
            self._pub.put(payload, attachment=attachment)
        self.sent += 1


@dataclass
class Received:
    """One sample handed to asyncio: payload bytes, key, attachment, arrival wall time [s]."""
    payload: bytes
    key: str
    attachment: bytes | None
    t_arrival_wall_s: float


class AsyncSubscriber:
    """Bridge from zenoh callback threads into an asyncio.Queue.

    ``await sub.get()`` returns the next ``Received``; ``sub.drain()`` returns everything queued
    now without waiting. With ``maxsize > 0`` a full queue drops the newest sample and counts it
    in ``dropped`` (the loop must never block a zenoh thread).
    """

    def __init__(self, link: Link, key: str, loop: asyncio.AbstractEventLoop, maxsize: int = 0):
        self.queue: asyncio.Queue[Received] = asyncio.Queue(maxsize)
        self.loop = loop
        self.received = 0
        self.dropped = 0
        self._sub = link.subscribe(key, self._on_sample)

    def _on_sample(self, payload: bytes, key: str, attachment: bytes | None, t_arr: float) -> None:
        self.received += 1
        try:
            self.loop.call_soon_threadsafe(self._put, Received(payload, key, attachment, t_arr))
        except RuntimeError:  # loop already closed during shutdown
            self.dropped += 1

    def _put(self, item: Received) -> None:
        try:
            self.queue.put_nowait(item)
        except asyncio.QueueFull:
            self.dropped += 1

    async def get(self) -> Received:
        return await self.queue.get()

    def drain(self) -> list[Received]:
        out = []
        while True:
            try:
                out.append(self.queue.get_nowait())
            except asyncio.QueueEmpty:
                return out


@dataclass
class LinkImpairment:
    """Injected link delay of a slave, for tests and trials of the master's latency handling
    (never set on a vehicle): base ``latency_ms``, Gaussian ``jitter_ms`` (1-sigma, clipped to
    +-3 sigma, delay >= 0) and delay ``spikes`` as (t_start_gps_s, t_end_gps_s, extra_ms) in GPS
    seconds of the messages' time of validity; ``seed`` of the jitter draws. The slave sends message k at
    ``max(send_{k-1}, t_k + delay_k)``: a FIFO link, jitter changes spacing, never the order."""
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    spikes: list[tuple[float, float, float]] = field(default_factory=list)
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.latency_ms > 0 or self.jitter_ms > 0 or bool(self.spikes)

    def delays_s(self, t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Delay [s] of messages valid at ``t_s`` (same time axis as the spikes), before FIFO ordering."""
        t_s = np.asarray(t_s, float)
        j = np.clip(rng.normal(0.0, 1.0, len(t_s)), -3.0, 3.0) * self.jitter_ms
        d = np.maximum(0.0, self.latency_ms + j)
        for t0, t1, extra in self.spikes:
            d = d + np.where((t_s >= t0) & (t_s < t1), extra, 0.0)
        return d / 1000.0


def run_router(listen: list[str], connect: list[str] | None = None) -> int:
    """A standalone zenoh router (for a router mesh) until SIGTERM/SIGINT: ``python -m v2xpos.link
    --router tcp/127.0.0.1:7447 [--connect tcp/127.0.0.1:7448 ...]``."""
    import signal
    import threading
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    link = Link(LinkConfig(mode="router", listen=list(listen), connect=list(connect or [])))
    print(f"v2xpos router listening on {listen}, connecting to {connect or []}", flush=True)
    try:
        stop.wait()
    finally:
        link.close()
    return 0


if __name__ == "__main__":
    import argparse
    import sys
    ap = argparse.ArgumentParser(prog="python -m v2xpos.link", description="standalone loopback zenoh router")
    ap.add_argument("--router", action="append", required=True, metavar="ENDPOINT", help="listen endpoint")
    ap.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="other routers")
    a = ap.parse_args()
    sys.exit(run_router(a.router, a.connect))
