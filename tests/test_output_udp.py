"""UDP output: loopback roundtrip through a real socket, refusal of remote destinations, parser errors."""
import math
import socket
import struct

import numpy as np
import pytest

from v2xpos.output.udp import (HEADER, LaneRecord, ObjectRecord, UdpFormatError, UdpOutput, build_datagram,
                               parse_datagram)
from v2xpos.wire import FixSide, RelativeResult, TargetStatus


def valid(target_id="car-2", **kw) -> RelativeResult:
    base = dict(target_id=target_id, source_seq=41, latency_s=0.1, rel_pos_body_m=np.array([1234.5678, -12.3456, 0.5]),
                rel_pos_sd_m=np.array([0.01, 0.02, 0.03]), rel_vel_body_mps=np.array([-4.5, 0.25, 0.0]),
                rel_acc_body_mps2=np.array([1.0, -0.5, 0.0]), rel_rpy_rad=np.array([0.01, -0.02, 1.2]),
                range_m=1234.63, range_sd_m=0.011, bearing_rad=-0.01, elevation_rad=-0.0004,
                longitudinal_m=1230.1, lateral_m=-11.5, gap_m=1230.2, closing_speed_mps=4.5, ttc_s=273.4)
    base.update(kw)
    return RelativeResult(**base)


@pytest.fixture
def receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def test_roundtrip_on_loopback(receiver):
    port = receiver.getsockname()[1]
    results = [valid(), valid("ped-1", target_kind="pedestrian", degraded=True, ttc_s=None),
               RelativeResult(target_id="car-3", status=TargetStatus.FIX_INVALID, fix_side=FixSide.MASTER,
                              latency_s=0.02, source_seq=7)]
    lanes = [LaneRecord(0, 1.8, -0.2), LaneRecord(2, -1.7, 0.1)]
    objects = [ObjectRecord(4, 1, 25.0, 0.3, 5.0, 5.0), ObjectRecord(5, 0, 3.0, -1.0, math.nan, -1.0)]
    with UdpOutput("127.0.0.1", port) as out:
        n = out.send(results, seq=99, t_gps_s=1_400_000_000.125, lanes=lanes, objects=objects)
        assert out.datagrams_sent == 1
    data = receiver.recv(65536)
    assert len(data) == n
    d = parse_datagram(data)
    assert d.seq == 99 and d.t_gps_s == 1_400_000_000.125
    a, p, c = d.targets
    assert a.target_id == "car-2" and a.status == TargetStatus.VALID and a.source_seq == 41
    np.testing.assert_allclose(a.rel_pos_body_m, results[0].rel_pos_body_m, atol=1e-9)    # float64
    np.testing.assert_allclose(a.rel_vel_body_mps, results[0].rel_vel_body_mps, atol=1e-5)  # float32
    assert a.range_m == pytest.approx(1234.63, abs=1e-9) and a.ttc_s == pytest.approx(273.4, rel=1e-6)
    assert a.latency_s == pytest.approx(0.1, rel=1e-6) and a.lateral_m == pytest.approx(-11.5, abs=1e-4)
    assert p.target_kind == "pedestrian" and p.degraded and p.ttc_s is None
    assert c.status == TargetStatus.FIX_INVALID and c.fix_side == FixSide.MASTER and math.isnan(c.range_m)
    assert [l.index for l in d.lanes] == [0, 2] and d.lanes[0].lateral_m == pytest.approx(1.8, abs=1e-6)
    assert d.objects[0].kind == 1 and math.isnan(d.objects[1].ttc_s)


@pytest.mark.parametrize("host", ["10.0.0.5", "192.168.1.20", "8.8.8.8", "example.com"])
def test_remote_destinations_refused(host):
    with pytest.raises(ValueError, match="not loopback"):
        UdpOutput(host, 40000)


def test_multicast_refused_even_with_allow_remote():
    with pytest.raises(ValueError, match="multicast"):
        UdpOutput("239.1.2.3", 40000, allow_remote=True)


def test_localhost_and_ipv4_loopback_allowed():
    UdpOutput("localhost", 40000).close()
    UdpOutput("127.0.0.2", 40000).close()


def test_parse_errors_say_what_and_where():
    good = build_datagram([valid()], 1, 2.0)
    with pytest.raises(UdpFormatError, match="header"):
        parse_datagram(good[:10])
    with pytest.raises(UdpFormatError, match="bad magic"):
        parse_datagram(b"XXXX" + good[4:])
    with pytest.raises(UdpFormatError, match="unknown version"):
        parse_datagram(good[:4] + bytes([9]) + good[5:])
    with pytest.raises(UdpFormatError, match="length") as info:
        parse_datagram(good[:-3])
    assert info.value.offset == 6
    bad_status = bytearray(good)
    bad_status[HEADER.size + 32] = 200
    with pytest.raises(UdpFormatError, match="unknown target status"):
        parse_datagram(bytes(bad_status))
    assert struct.unpack_from("<4s", good)[0] == b"V2XR"
