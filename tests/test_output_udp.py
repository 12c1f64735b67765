"""UDP output: roundtrip through a real socket to a configured host (127.0.0.1), per-record time of
validity and fix states, refusal of multicast / broadcast destinations, parser errors."""
import math
import socket
import struct

import numpy as np
import pytest

from v2xpos.output.udp import (HEADER, TARGET, TARGET_V1, TARGET_V2, LaneRecord, ObjectRecord, UdpFormatError,
                               UdpOutput, build_datagram, check_destination, parse_datagram)
from v2xpos.types import FilterReason, FixStatus
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


@pytest.mark.parametrize("host, why", [("239.1.2.3", "multicast"), ("ff02::1", "multicast"),
                                       ("255.255.255.255", "broadcast"), ("0.0.0.0", "unspecified"),
                                       ("::", "unspecified"), ("", "empty")])
def test_multicast_broadcast_and_unspecified_refused(host, why):
    with pytest.raises(ValueError, match=why):
        check_destination(host)
    with pytest.raises(ValueError, match=why):
        UdpOutput(host, 40000)


@pytest.mark.parametrize("host", ["10.0.0.5", "192.168.1.20", "127.0.0.2", "localhost", "::1"])
def test_unicast_destinations_accepted(host):
    """Any configured unicast host (a socket is opened, nothing is sent in this test)."""
    check_destination(host)
    UdpOutput(host, 40000).close()


def test_bad_port_and_unresolvable_name_refused():
    with pytest.raises(ValueError, match="port"):
        UdpOutput("127.0.0.1", 0)
    with pytest.raises(ValueError, match="cannot resolve"):
        UdpOutput("no-such-host.invalid", 40000)


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


def test_records_carry_their_own_time_of_validity_fix_states_and_sigmas(receiver):
    """Records of one datagram valid 50 ms apart keep their own times; a float spell on the target
    shows as target_fix FLOAT (VALID) and SINGLE (FIX_INVALID) per record."""
    port = receiver.getsockname()[1]
    t0 = 1_400_000_000.0
    results = [valid(seq=101, t_gps_s=t0, master_fix=FixStatus.FIXED, target_fix=FixStatus.FIXED,
                     rel_yaw_sd_rad=0.004),
               valid(seq=102, t_gps_s=t0 + 0.02, master_fix=FixStatus.FIXED, target_fix=FixStatus.FLOAT,
                     rel_pos_sd_m=np.array([0.21, 0.18, 0.4]), rel_yaw_sd_rad=0.011),
               RelativeResult(target_id="car-2", seq=103, t_gps_s=t0 + 0.05, status=TargetStatus.FIX_INVALID,
                              fix_side=FixSide.SLAVE, master_fix=FixStatus.FIXED, target_fix=FixStatus.SINGLE),
               valid("car-3", seq=104, t_gps_s=t0 + 0.05, status=TargetStatus.ATTITUDE_UNCERTAIN,
                     master_fix=FixStatus.FLOAT, target_fix=FixStatus.FIXED, rel_yaw_sd_rad=0.3)]
    with UdpOutput("127.0.0.1", port) as out:
        out.send(results, seq=104, t_gps_s=t0 + 0.05)
    d = parse_datagram(receiver.recv(65536))
    assert d.version == 3 and len(d.targets) == 4
    assert [r.t_gps_s for r in d.targets] == [t0, t0 + 0.02, t0 + 0.05, t0 + 0.05]
    assert [r.seq for r in d.targets] == [101, 102, 103, 104]
    assert [r.target_fix for r in d.targets] == [FixStatus.FIXED, FixStatus.FLOAT, FixStatus.SINGLE, FixStatus.FIXED]
    assert [r.master_fix for r in d.targets] == [FixStatus.FIXED] * 3 + [FixStatus.FLOAT]
    fl = d.targets[1]
    np.testing.assert_allclose(fl.rel_pos_sd_m, [0.21, 0.18, 0.4], rtol=1e-6)
    assert fl.rel_yaw_sd_rad == pytest.approx(0.011, rel=1e-6) and fl.range_sd_m == pytest.approx(0.011, rel=1e-6)
    bad = d.targets[2]
    assert bad.status == TargetStatus.FIX_INVALID and math.isnan(bad.rel_yaw_sd_rad) and math.isnan(bad.range_m)
    unc = d.targets[3]   # kinematics with a status that says why it is not VALID
    assert unc.status == TargetStatus.ATTITUDE_UNCERTAIN and unc.has_kinematics
    assert unc.range_m == pytest.approx(1234.63) and unc.rel_yaw_sd_rad == pytest.approx(0.3, rel=1e-6)


def test_records_say_which_vehicle_and_why_and_the_protection_level(receiver):
    """Version 3: a non-VALID record names the vehicle (reason_side), both filters' reasons and the
    relative protection level; the heartbeat says the master is alive when it has nothing else."""
    port = receiver.getsockname()[1]
    unverified = valid(status=TargetStatus.UNVERIFIED, reason_side=FixSide.SLAVE, master_reason=0,
                       target_reason=int(FilterReason.SETUP_UNVERIFIED), protection_m=0.31)
    failed = valid("car-3", status=TargetStatus.INCONSISTENT, reason_side=FixSide.MASTER,
                   master_reason=int(FilterReason.TEST_POSITION))
    with UdpOutput("127.0.0.1", port) as out:
        out.send([unverified, failed], seq=5, t_gps_s=1_400_000_000.0)
        out.send_heartbeat(6, 1_400_000_000.1)
    d = parse_datagram(receiver.recv(65536))
    u, f = d.targets
    assert (u.status, u.reason_side, u.target_reason) == (TargetStatus.UNVERIFIED, FixSide.SLAVE,
                                                          FilterReason.SETUP_UNVERIFIED)
    assert u.protection_m == pytest.approx(0.31, rel=1e-6) and math.isnan(f.protection_m)
    assert (f.status, f.reason_side, f.master_reason) == (TargetStatus.INCONSISTENT, FixSide.MASTER,
                                                          FilterReason.TEST_POSITION)
    hb = parse_datagram(receiver.recv(65536))
    assert hb.heartbeat and not hb.targets and hb.t_gps_s == 1_400_000_000.1 and not d.heartbeat


def test_version_2_datagrams_still_parse():
    rec = TARGET_V2.pack(b"car-2", 8, 0, 0, 5, 4, 1_400_000_000.0, 41, 9, 0.1, *([0.5] * 15), 3.0, *([0.1] * 8),
                         0.01)
    r = parse_datagram(HEADER.pack(b"V2XR", 2, 0, 1, 0, 0, 9, 1_400_000_000.0) + rec).targets[0]
    assert r.status == TargetStatus.INCONSISTENT and r.target_fix == FixStatus.FLOAT
    assert r.reason_side == FixSide.NONE and math.isnan(r.protection_m) and r.range_m == 3.0
    rec9 = TARGET_V2.pack(b"car-2", 9, 0, 0, 5, 4, 1_400_000_000.0, 41, 9, 0.1, *([0.5] * 15), 3.0, *([0.1] * 8),
                          0.01)
    with pytest.raises(UdpFormatError, match="version 2"):
        parse_datagram(HEADER.pack(b"V2XR", 2, 0, 1, 0, 0, 9, 1_400_000_000.0) + rec9)


def test_version_1_datagrams_still_parse():
    t = 1_400_000_000.5
    rec = TARGET_V1.pack(b"car-2", 0, 0, 2, 0, 41, 0.1, 1.0, 2.0, 3.0, *([0.01] * 3), *([0.0] * 9), 3.74,
                         *([0.0] * 8))
    data = HEADER.pack(b"V2XR", 1, 0, 1, 0, 0, 7, t) + rec
    d = parse_datagram(data)
    r = d.targets[0]
    assert d.version == 1 and r.t_gps_s == t and r.seq == 7 and r.source_seq == 41
    assert r.target_kind == "pedestrian" and r.range_m == pytest.approx(3.74)
    assert r.master_fix == FixStatus.NONE and math.isnan(r.rel_yaw_sd_rad)
    assert TARGET.size == 184 and TARGET_V1.size == 160


def test_unknown_fix_code_is_a_format_error():
    data = bytearray(build_datagram([valid(master_fix=FixStatus.FIXED)], 1, 2.0))
    data[HEADER.size + 35] = 9
    with pytest.raises(UdpFormatError, match="master fix status 9") as info:
        parse_datagram(bytes(data))
    assert info.value.offset == HEADER.size + 35
