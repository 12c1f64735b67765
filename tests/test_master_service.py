"""The master service in-process (embedded router, real zenoh on loopback) in both dispatch modes:
a client publishes a target's states (and one malformed payload); results come back on the
relative key, status JSON on the status key, the rejection is counted, shutdown is clean."""
from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest

from master.config import MasterConfig
from master.service import MasterService
from v2xpos.launch import free_tcp_port
from v2xpos.link import Link, LinkConfig, loopback_endpoint
from v2xpos.wire import (StateMessage, TargetStatus, decode_relative, encode_state, relative_key, state_key,
                         status_key)


def state_at(svc: MasterService, vid: str, seq: int, t: float) -> bytes:
    from tests.test_master_pipeline import truth_state
    sc = svc.source.sc
    msg = StateMessage.from_nav_state(truth_state(sc, vid, t), "svc", vid, seq,
                                      geometry=sc.actors[vid].geometry, t_sent_wall_s=time.time())
    return encode_state(msg)


@pytest.mark.slow
@pytest.mark.parametrize("dispatch", ["inline", "asyncio"])
async def test_master_service_round_trip(dispatch):
    port = free_tcp_port()
    cfg = MasterConfig.from_dict({
        "service": {"fleet": "svc", "master_id": "ego", "dispatch": dispatch, "status_hz": 5.0,
                    "measurement_point_m": [3.8, 0.0, 0.0]},
        "link": {"mode": "router", "listen": [loopback_endpoint(port)]},
        "source": {"type": "sim", "factory": "sim.source:from_config", "model": "truth_noise",
                   "start_unix_s": time.time() + 1.0,
                   "params": {"vehicles": 2, "duration_s": 30.0, "pedestrian": False, "history_s": 0.0}},
        "output": {"zenoh": {"enabled": True}}}, "test.toml")
    svc = MasterService(cfg)
    task = asyncio.create_task(svc.run())
    client = None
    try:
        t_end = time.time() + 20.0
        while svc.link is None and time.time() < t_end:
            await asyncio.sleep(0.05)
        client = Link(LinkConfig(mode="client", connect=[loopback_endpoint(port)], connect_timeout_ms=10000))
        results, statuses = [], []
        client.subscribe(relative_key("svc", "ego"), lambda p, k, a, t: results.append(decode_relative(p)))
        client.subscribe(status_key("svc", "ego"), lambda p, k, a, t: statuses.append(json.loads(p)))
        pub = client.publisher(state_key("svc", "t1"))
        while svc.nav is None and time.time() < t_end:
            await asyncio.sleep(0.05)
        for seq in range(1, 151):
            pub.put(state_at(svc, "t1", seq, svc.gps_now() - 0.05))
            if seq == 10:
                pub.put(b"\x93not a state")      # counted for t1 (its track exists by now)
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.6)
        svc.stop_event.set()
        final = await asyncio.wait_for(task, 30.0)
    finally:
        if client is not None:
            client.close()
        if not task.done():
            svc.stop_event.set()
            await asyncio.wait_for(task, 30.0)
    assert final["dispatch"] == dispatch
    assert final["rejected"] == {"malformed": 1}
    assert final["targets"]["t1"]["accepted"] == 150 and final["targets"]["t1"]["rejected"] == {"malformed": 1}
    from_msgs = [r for r in results if r.target_id == "t1" and r.status == TargetStatus.VALID]
    assert len(from_msgs) >= 140 and all(np.isfinite(r.rel_pos_body_m).all() for r in from_msgs)
    assert all(8.0 < r.range_m < 25.0 for r in from_msgs)       # t1 drives 7.5-15 m ahead
    assert statuses and statuses[-1]["targets"]["t1"]["accepted"] > 0
    assert svc.link.session.is_closed()


def test_realtime_priority_applied_or_refused_with_a_message(capsys):
    """SCHED_RR where permitted (threads created afterwards inherit it), else normal priority
    with a message; 0 leaves the scheduling alone."""
    import os
    import threading

    from v2xpos.launch import apply_realtime_priority
    assert apply_realtime_priority(0) is False
    result = {}

    def worker():
        before = os.sched_getscheduler(0)
        result["granted"] = apply_realtime_priority(5)
        seen = {}
        child = threading.Thread(target=lambda: seen.update(policy=os.sched_getscheduler(0)))
        child.start()
        child.join()
        result["child"] = seen["policy"]
        os.sched_setscheduler(0, before, os.sched_param(0))

    t = threading.Thread(target=worker)   # only this thread's policy changes, and it is restored
    t.start()
    t.join()
    if result["granted"]:
        assert result["child"] == os.SCHED_RR
    else:
        assert "not granted" in capsys.readouterr().err
