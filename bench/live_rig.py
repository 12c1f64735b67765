"""A live V2V rig on loopback for the trust bench and its tests: a master session embedding the
zenoh router (``tcp/127.0.0.1:PORT``) that runs ``master.pipeline.MasterPipeline`` with a
``MessageAuthenticator`` (trust list of the rig's vehicles) on every sample, and slave sessions that
publish signed StateMessages. Link impairments are applied at the sender by the scenarios
(``bench.trust``, ``bench.trust_faults``)."""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from v2xpos.launch import free_tcp_port
from v2xpos.types import FixStatus, NavState
from v2xpos.wire import STATE_KEY_ALL, Geometry, StateMessage, encode_state, state_key

FLEET = "fault"
EPOCH_GPS_S = 1.4e9
RATE_HZ = 100.0
DEFAULT_TIMEOUT_S = 0.2


@dataclass
class Delivered:
    """A result the master produced: its status and the payload that caused it (None for ticks)."""
    t_now_gps_s: float
    result: object
    payload: bytes | None
    t_arrival_wall_s: float = math.nan
    master_fix: FixStatus | None = None


def master_nav(t: float, fix: FixStatus, lat0: float = 0.6981317, lon0: float = -1.8325957) -> NavState:
    """Master state: straight north at 20 m/s from (lat0, lon0) at EPOCH_GPS_S."""
    return NavState(t_s=t, lla=np.array([lat0 + 20.0 * (t - EPOCH_GPS_S) / 6.38e6, lon0, 1600.0]),
                    v_ned_mps=np.array([20.0, 0.0, 0.0]), acc_body_mps2=np.zeros(3),
                    rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3), pos_sd_m=np.full(3, 0.01),
                    vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.full(3, 1e-3), fix=fix)


class LiveRig:
    """Master (router + pipeline + authenticator) and slave sessions on loopback.

    ``send(vid, seq, t_valid_s, fix)`` publishes a signed state of vehicle ``vid`` now;
    ``master_fix`` sets the master's own fix; ``delivered`` collects every result with the
    payload behind it; ``accepted_payloads`` is the set of payloads that produced a result.
    """

    def __init__(self, vehicles=("car1", "car2"), timeout_s: float = DEFAULT_TIMEOUT_S, port: int | None = None,
                 master_mode: str = "router", router_endpoint: str | None = None):
        from master.pipeline import MasterPipeline, PipelineConfig
        from v2xpos.link import Link, LinkConfig
        from v2xpos.security import Ed25519PrivateKey, MessageAuthenticator, MessageSigner, TrustList

        self.port = port or free_tcp_port()
        self.endpoint = router_endpoint or f"tcp/127.0.0.1:{self.port}"
        self.signers = {v: MessageSigner(Ed25519PrivateKey.generate()) for v in vehicles}
        trust = TrustList()
        for v, s in self.signers.items():
            trust.add(v, s.public_key)
        self.auth = MessageAuthenticator(trust)
        self.delivered: list[Delivered] = []
        self.accepted_payloads: set[bytes] = set()
        self.pipe = MasterPipeline(PipelineConfig(fleet=FLEET, master_id="ego", timeout_s=timeout_s,
                                                  measurement_point_m=(3.8, 0.0, 0.0), known_vehicles=tuple(vehicles)),
                                   [], authenticator=self.auth)
        self.master_fix = FixStatus.FIXED
        self.lock = threading.Lock()
        self.t0 = time.time()
        if master_mode == "router":
            self.master_link = Link(LinkConfig(mode="router", listen=[self.endpoint]))
        else:
            self.master_link = Link(LinkConfig(mode=master_mode, connect=[self.endpoint]))
        self.master_link.subscribe(STATE_KEY_ALL(FLEET), self._on_sample)
        self.slave_link = Link(LinkConfig(mode="peer" if master_mode == "router" else "client",
                                          connect=[self.endpoint]))
        self.pubs = {v: self.slave_link.publisher(state_key(FLEET, v)) for v in vehicles}
        self.geometry = Geometry.box(3.8, 1.0, 0.9)
        self.last_arrival_wall_s = math.nan

    def now(self) -> float:
        return EPOCH_GPS_S + (time.time() - self.t0)

    def _on_sample(self, payload: bytes, key: str, att, t_arr: float) -> None:
        with self.lock:
            self.last_arrival_wall_s = t_arr
            now = self.now()
            fix = self.master_fix
            res = self.pipe.handle(payload, key, master_nav(now, fix), now, t_arr)
            if res is not None:
                self.accepted_payloads.add(payload)
                self.delivered.append(Delivered(now, res, payload, t_arr, fix))

    def tick(self) -> None:
        with self.lock:
            now = self.now()
            for res in self.pipe.tick(now, now):
                self.delivered.append(Delivered(now, res, None))

    def state(self, vid: str, seq: int, t_valid_s: float, fix: FixStatus = FixStatus.FIXED) -> StateMessage:
        idx = list(self.signers).index(vid) if vid in self.signers else 0
        n = master_nav(t_valid_s, fix)
        n.lla = n.lla + np.array([(15.0 + 10.0 * idx) / 6.38e6, (3.5 * (idx % 2)) / 4.9e6, 0.0])
        return StateMessage.from_nav_state(n, FLEET, vid, seq, geometry=self.geometry, t_sent_wall_s=time.time())

    def encode(self, vid: str, seq: int, t_valid_s: float, fix: FixStatus = FixStatus.FIXED,
               signer=None) -> bytes:
        return encode_state(self.state(vid, seq, t_valid_s, fix), sign=signer or self.signers[vid])

    def put(self, vid: str, payload: bytes) -> None:
        self.pubs[vid].put(payload)

    def results(self, vid: str) -> list[Delivered]:
        return [d for d in self.delivered if d.result.target_id == vid]

    def settle(self, s: float = 0.3) -> None:
        time.sleep(s)

    def close(self) -> None:
        self.slave_link.close()
        self.master_link.close()


def paced(n_steps: int, rate: float = RATE_HZ):
    """Yield step indices at ``rate`` Hz (absolute schedule)."""
    t0 = time.time()
    for k in range(n_steps):
        delay = t0 + k / rate - time.time()
        if delay > 0:
            time.sleep(delay)
        yield k


def wait_connected(rig: LiveRig, vid: str = "car1", timeout_s: float = 5.0) -> None:
    """Send probes until the master receives one (routes established)."""
    deadline = time.time() + timeout_s
    seq = 0
    while time.time() < deadline:
        rig.put(vid, rig.encode(vid, 10 ** 9 + seq, rig.now() - 0.002))
        seq += 1
        time.sleep(0.05)
        if rig.delivered:
            break
    with rig.lock:
        rig.delivered.clear()
        rig.accepted_payloads.clear()


def fresh_rig(**kw) -> LiveRig:
    """A connected rig whose master has forgotten the connection probes."""
    from master.pipeline import TargetTrack
    rig = LiveRig(**kw)
    wait_connected(rig)
    with rig.lock:
        for v in rig.signers:
            rig.pipe.tracks[v] = TargetTrack(v)
        rig.auth.reset_replay_windows()
        rig.pipe.rejected.clear()
    return rig

