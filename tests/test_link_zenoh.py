"""v2xpos.link: loopback-only zenoh configuration, pub/sub through an embedded router, the asyncio
bridge (order, no loss with BLOCK), config errors naming the key, deterministic close."""
from __future__ import annotations

import asyncio
import json
import time

import pytest

from v2xpos.launch import free_tcp_port
from v2xpos.link import Link, LinkConfig, loopback_endpoint
from v2xpos.wire import STATE_KEY_ALL, state_key, status_key


def test_config_is_loopback_only_and_validated():
    cfg = LinkConfig(mode="router", listen=[loopback_endpoint(17411)])
    z = cfg.to_zenoh()
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    assert json.loads(z.get_json("scouting/gossip/enabled")) is False
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17411"]
    assert json.loads(z.get_json("connect/retry"))["period_max_ms"] == 500
    with pytest.raises(ValueError, match=r"\[link\].*unknown key"):
        LinkConfig.from_dict({"mode": "peer", "conect": []}, "[link]")
    with pytest.raises(ValueError, match="mode"):
        LinkConfig.from_dict({"mode": "broker"}, "[link]")
    with pytest.raises(ValueError, match="locator"):
        LinkConfig(connect=["127.0.0.1:7447"])
    with pytest.raises(ValueError):
        loopback_endpoint(70000)


async def test_async_bridge_delivers_all_in_order_through_router():
    port = free_tcp_port()
    router = Link(LinkConfig(mode="router", listen=[loopback_endpoint(port)]))
    slave = Link(LinkConfig(mode="peer", connect=[loopback_endpoint(port)]))
    try:
        sub = router.subscribe_async(STATE_KEY_ALL("fleetx"))
        pubs = {vid: slave.publisher(state_key("fleetx", vid)) for vid in ("a", "b")}
        other = slave.publisher(status_key("fleetx", "m"))          # not matched by the subscription
        t_end = time.time() + 5.0
        while time.time() < t_end:                                  # wait for the route to exist
            pubs["a"].put(b"probe")
            try:
                await asyncio.wait_for(sub.get(), 0.1)
                break
            except asyncio.TimeoutError:
                pass
        sub.drain()
        n = 400
        for i in range(n):
            for vid, p in pubs.items():
                p.put(f"{vid}:{i}".encode(), attachment=b"att")
            other.put(b"ignored")
        got = []
        t_end = time.time() + 5.0
        while len(got) < 2 * n and time.time() < t_end:
            try:
                got.append(await asyncio.wait_for(sub.get(), 0.5))
            except asyncio.TimeoutError:
                pass
        assert len(got) == 2 * n and sub.dropped == 0
        for vid in ("a", "b"):
            seq = [int(g.payload.decode().split(":")[1]) for g in got if g.key == state_key("fleetx", vid)]
            assert seq == list(range(n))
        assert all(g.attachment == b"att" and g.t_arrival_wall_s > 0 for g in got)
    finally:
        slave.close()
        router.close()
    assert router.session.is_closed() and slave.session.is_closed()
    router.close()                                                  # idempotent


def test_router_mesh_by_config_only():
    """Standalone router process A, in-process router B meshed to A; the 'master' is a peer on A,
    the 'slave' a peer on B: states and results flow across the mesh."""
    import subprocess
    import sys
    from pathlib import Path
    pa, pb = free_tcp_port(), free_tcp_port()
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-m", "v2xpos.link", "--router", loopback_endpoint(pa)], cwd=root,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    links = []
    try:
        links.append(Link(LinkConfig(mode="router", listen=[loopback_endpoint(pb)], connect=[loopback_endpoint(pa)])))
        master = Link(LinkConfig(mode="peer", connect=[loopback_endpoint(pa)]))
        slave = Link(LinkConfig(mode="peer", connect=[loopback_endpoint(pb)]))
        links += [master, slave]
        got, back = [], []
        master.subscribe(STATE_KEY_ALL("mesh"), lambda p, k, a, t: got.append(p))
        slave.subscribe("v2xpos/mesh/master/*/relative", lambda p, k, a, t: back.append(p))
        pub = slave.publisher(state_key("mesh", "t1"))
        rel = master.publisher("v2xpos/mesh/master/ego/relative")
        t_end = time.time() + 10.0
        while (not got or not back) and time.time() < t_end:
            pub.put(b"state")
            rel.put(b"result")
            time.sleep(0.05)
        assert got and back and proc.poll() is None
    finally:
        for link in reversed(links):
            link.close()
        proc.terminate()
        assert proc.wait(timeout=10) == 0
