"""Master pipeline (in-process, no network): validation and rejection counting, fix gating, staleness,
latency compensation on a turning target, and the CAN / UDP outputs against the results."""
from __future__ import annotations

import math

import can
import numpy as np
import pytest

from master.outputs import CanSink, UdpSink
from master.pipeline import MasterPipeline, PipelineConfig
from sim.evaluate import truth_relative
from sim.scenarios import build
from v2xpos.output.can import decode_frames
from v2xpos.output.udp import parse_datagram
from v2xpos.types import FixStatus, NavState
from v2xpos.wire import Geometry, StateMessage, TargetStatus, encode_state

FLEET = "demo"


@pytest.fixture(scope="module")
def scenario():
    return build("convoy", vehicles=3, duration_s=20.0, seed=3, pedestrian=False, degradations=False, spikes=False)


def truth_state(sc, actor_id: str, t_s: float, fix: FixStatus = FixStatus.FIXED) -> NavState:
    s = sc.actors[actor_id].truth.sample(t_s)
    return NavState(t_s=t_s, lla=s["lla"][0], v_ned_mps=s["v_ned_mps"][0], acc_body_mps2=s["acc_body_mps2"][0],
                    rate_body_rps=s["w_nb_b_rps"][0], rpy_rad=s["rpy_rad"][0], pos_sd_m=np.full(3, 0.01),
                    vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.full(3, 0.001), fix=fix)


def payload(sc, actor_id: str, seq: int, t_s: float, fix: FixStatus = FixStatus.FIXED) -> bytes:
    msg = StateMessage.from_nav_state(truth_state(sc, actor_id, t_s, fix), FLEET, actor_id, seq,
                                      geometry=sc.actors[actor_id].geometry, kind=sc.actors[actor_id].kind,
                                      t_sent_wall_s=1.0)
    return encode_state(msg)


def key(vid: str) -> str:
    return f"v2xpos/{FLEET}/vehicle/{vid}/state"


def make_pipeline(sc, sinks=None, **kw) -> MasterPipeline:
    cfg = PipelineConfig(fleet=FLEET, master_id="ego", measurement_point_m=(3.8, 0.0, 0.0),
                         known_vehicles=tuple(a.actor_id for a in sc.slaves), evaluate_uncompensated=True,
                         record=True, **kw)
    return MasterPipeline(cfg, sinks or [], clock_wall=lambda: 2.0)


def test_rejections_are_counted_and_do_not_disturb_other_targets(scenario):
    sc = scenario
    pipe = make_pipeline(sc)
    t0 = sc.epoch_gps_s + 5.0
    results = []
    for k in range(20):
        t = t0 + 0.01 * k
        master = truth_state(sc, "ego", t)
        results.append(pipe.handle(payload(sc, "t2", k + 1, t - 0.05), key("t2"), master, t))
        junk = [b"\x00garbage", payload(sc, "t1", k + 1, t - 0.05)[:-7], b""]
        assert pipe.handle(junk[k % 3], key("t1"), master, t) is None
    assert all(r is not None and r.status == TargetStatus.VALID for r in results)
    master = truth_state(sc, "ego", t0 + 0.3)
    good = payload(sc, "t1", 5, t0 + 0.25)
    assert pipe.handle(good, key("t1"), master, t0 + 0.3).status == TargetStatus.VALID
    assert pipe.handle(good, key("t1"), master, t0 + 0.3) is None                       # duplicate
    assert pipe.handle(payload(sc, "t1", 4, t0 + 0.24), key("t1"), master, t0 + 0.3) is None  # older seq
    assert pipe.handle(payload(sc, "t1", 6, t0 + 0.20), key("t1"), master, t0 + 0.3) is None  # time going back
    assert pipe.handle(payload(sc, "t1", 7, t0 + 0.26), key("t2"), master, t0 + 0.3) is None  # key mismatch
    intruder = StateMessage.from_nav_state(truth_state(sc, "t1", t0), FLEET, "x9", 1)
    assert pipe.handle(encode_state(intruder), key("x9"), master, t0 + 0.3) is None           # unknown
    assert pipe.rejected["malformed"] == 20
    assert pipe.rejected["duplicate"] == 1 and pipe.rejected["out_of_order"] == 2
    assert pipe.rejected["key_mismatch"] == 1 and pipe.rejected["unknown_vehicle"] == 1
    assert pipe.tracks["t1"].rejected["malformed"] == 20
    assert dict(pipe.tracks["t2"].rejected) == {"key_mismatch": 1}     # counted where it claimed to be
    assert pipe.tracks["t2"].results["valid"] == 20
    # the next good t2 message is still accepted and valid after all the noise on t1
    r = pipe.handle(payload(sc, "t2", 21, t0 + 0.29), key("t2"), master, t0 + 0.3)
    assert r.status == TargetStatus.VALID


@pytest.mark.slow
def test_fix_transitions_change_status_and_stop_outputs(scenario):
    """A float spell then a single spell on the target: VALID through float, FIX_INVALID on single; on
    CAN (decoded with cantools from the shipped DBC) and UDP every update says both vehicles' fix."""
    import socket

    import cantools

    from v2xpos.output.can_dbc import DBC_PATH, FRAMES_PER_KINEMATIC_UPDATE, FRAMES_PER_STATUS_UPDATE
    sc = scenario
    bus_rx = can.Bus(channel="test-fix", interface="virtual")
    can_sink = CanSink(channel="test-fix", interface="virtual")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    udp_sink = UdpSink("127.0.0.1", sock.getsockname()[1])
    pipe = make_pipeline(sc, [can_sink, udp_sink])
    t0 = sc.epoch_gps_s + 3.0
    sequence = [FixStatus.FIXED] * 5 + [FixStatus.FLOAT] * 5 + [FixStatus.SINGLE] * 5 + [FixStatus.FIXED] * 5
    statuses = []
    for k, fix in enumerate(sequence):
        t = t0 + 0.01 * k
        before = can_sink.frames
        r = pipe.handle(payload(sc, "t2", k + 1, t - 0.1, fix), key("t2"), truth_state(sc, "ego", t), t)
        statuses.append(r.status)
        assert r.target_fix == fix and r.master_fix == FixStatus.FIXED
        if r.status == TargetStatus.VALID:
            assert np.isfinite(r.rel_pos_body_m).all() and can_sink.frames - before == FRAMES_PER_KINEMATIC_UPDATE
        else:
            assert r.fix_side & 2 and np.isnan(r.rel_pos_body_m).all() and np.isnan(r.range_m)
            assert can_sink.frames - before == FRAMES_PER_STATUS_UPDATE    # status + id, no kinematics
    assert statuses[:10] == [TargetStatus.VALID] * 10
    assert statuses[10:15] == [TargetStatus.FIX_INVALID] * 5
    assert statuses[15:] == [TargetStatus.VALID] * 5
    # master side losing RTK also gates the pair
    r = pipe.handle(payload(sc, "t2", 99, t0 + 0.3), key("t2"), truth_state(sc, "ego", t0 + 0.35, FixStatus.SINGLE),
                    t0 + 0.35)
    assert r.status == TargetStatus.FIX_INVALID and r.fix_side & 1 and r.master_fix == FixStatus.SINGLE
    frames = []
    while (m := bus_rx.recv(timeout=0.0)) is not None:
        frames.append(m)
    assert len(frames) == can_sink.frames
    db = cantools.database.load_file(str(DBC_PATH))
    can_fix = [(str(d["T00_MasterFix"]), str(d["T00_TargetFix"]), str(d["T00_Status"]))
               for d in (db.decode_message(f.arbitration_id, f.data) for f in frames if f.arbitration_id == 0x200)]
    expect = ([("rtk_fixed", "rtk_fixed", "valid")] * 5 + [("rtk_fixed", "rtk_float", "valid")] * 5
              + [("rtk_fixed", "single", "fix_invalid")] * 5 + [("rtk_fixed", "rtk_fixed", "valid")] * 5
              + [("single", "rtk_fixed", "fix_invalid")])
    assert can_fix == expect
    udp = [parse_datagram(sock.recv(65536)).targets[0] for _ in range(len(sequence) + 1)]
    assert [(int(u.master_fix), int(u.target_fix)) for u in udp] == \
        [(int(FixStatus.FIXED), int(f)) for f in sequence] + [(int(FixStatus.SINGLE), int(FixStatus.FIXED))]
    can_sink.close()
    udp_sink.close()
    sock.close()
    bus_rx.shutdown()


def test_delay_spike_gives_timeout_and_never_a_stale_output(scenario):
    sc = scenario
    pipe = make_pipeline(sc)
    t0 = sc.epoch_gps_s + 8.0
    arrival = -math.inf
    n_timeout = 0
    for k in range(80):                          # FIFO link: a spike delays, never reorders
        t_valid = t0 + 0.01 * k
        arrival = max(arrival, t_valid + (0.35 if 20 <= k < 40 else 0.1))
        r = pipe.handle(payload(sc, "t1", k + 1, t_valid), key("t1"), truth_state(sc, "ego", arrival), arrival)
        assert r.latency_s == pytest.approx(arrival - t_valid)
        if arrival - t_valid > 0.2:
            n_timeout += 1
            assert r.status == TargetStatus.TIMEOUT and np.isnan(r.rel_pos_body_m).all()
        else:
            assert r.status == TargetStatus.VALID
    assert n_timeout >= 20
    t_now = arrival
    # silence: tick reports TIMEOUT for t1 after the timeout, NO_DATA for a target never heard
    t_late = t_now + 0.25
    ticks = {r.target_id: r for r in pipe.tick(t_late)}
    assert ticks["t1"].status == TargetStatus.TIMEOUT and np.isnan(ticks["t1"].rel_pos_body_m).all()
    assert ticks["t2"].status == TargetStatus.NO_DATA
    rows = pipe.records_arrays()["t1"]
    valid = rows[rows[:, 2] == 0]
    assert np.all(valid[:, 3] <= 0.2)                     # every kinematic output came from a fresh message


@pytest.mark.slow
def test_compensation_on_a_turning_target(scenario):
    """Cut-in target t1 during its lane change and the convoy curve: 100 ms old messages predicted
    with CTRA are within 2 cm of the truth at the master time; without compensation ~2 m off."""
    sc = scenario
    pipe = make_pipeline(sc)
    t1 = sc.actors["t1"].truth
    times = sc.epoch_gps_s + np.arange(2.0, 18.0, 0.05)
    rates = np.abs(t1.sample(times)["w_nb_b_rps"][:, 2])
    assert rates.max() > 0.05                                   # it does turn
    errs, unc = [], []
    for k, t in enumerate(times):
        r = pipe.handle(payload(sc, "t1", k + 1, t - 0.1), key("t1"), truth_state(sc, "ego", t), t)
        assert r.status == TargetStatus.VALID
        tr = truth_relative(sc, "t1", np.array([t]))
        errs.append(np.linalg.norm(r.rel_pos_body_m - tr["rel_pos_b_m"][0]))
        rows = pipe.records_arrays()["t1"][-1]
        unc.append(np.linalg.norm(np.array(rows[13:16]) - tr["rel_pos_b_m"][0]))
        assert abs(r.range_m - tr["range_m"][0]) < 0.03
    errs, unc = np.array(errs), np.array(unc)
    turning = rates > 0.05
    assert np.sqrt(np.mean(errs ** 2)) < 0.02 and errs[turning].max() < 0.05
    assert np.sqrt(np.mean(unc ** 2)) > 10 * np.sqrt(np.mean(errs ** 2))


def test_batch_sends_one_datagram_and_stamps_results_at_the_flush(scenario):
    """Inside ``pipeline.batch()`` the UDP sink queues; the block's end sends one datagram with every
    result in order, and the results count as written (pipeline time, record row) only then."""
    sc = scenario
    import socket
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    udp_sink = UdpSink("127.0.0.1", sock.getsockname()[1])
    clock = [10.0]
    pipe = make_pipeline(sc, [udp_sink])
    pipe.clock_wall = lambda: clock[0]
    t = sc.epoch_gps_s + 6.0
    with pipe.batch():
        results = [pipe.handle(payload(sc, vid, 1, t - 0.1), key(vid), truth_state(sc, "ego", t), t, 10.0)
                   for vid in ("t1", "t2")]
        assert udp_sink.datagrams == 0 and pipe.processed == 0 and not pipe.records
        clock[0] = 10.004                              # the flush happens 4 ms after arrival
    assert udp_sink.datagrams == 1 and pipe.processed == 2
    dg = parse_datagram(sock.recv(65536))
    assert [r.target_id for r in dg.targets] == ["t1", "t2"] and dg.seq == results[-1].seq
    for got, r in zip(dg.targets, results):
        assert got.status == r.status and np.allclose(got.rel_pos_body_m, r.rel_pos_body_m, atol=1e-9)
    rows = pipe.records_arrays()
    from master.pipeline import RECORD_FIELDS
    i_pipe = RECORD_FIELDS.index("pipeline_ms")
    assert rows["t1"].shape == (1, len(RECORD_FIELDS))
    assert rows["t1"][0, i_pipe] == pytest.approx(4.0) and rows["t2"][0, i_pipe] == pytest.approx(4.0)
    # outside a batch every result is flushed at once: one datagram each
    pipe.handle(payload(sc, "t1", 2, t), key("t1"), truth_state(sc, "ego", t + 0.01), t + 0.01, 10.004)
    assert udp_sink.datagrams == 2 and len(parse_datagram(sock.recv(65536)).targets) == 1
    udp_sink.close()
    sock.close()


def test_can_and_udp_outputs_equal_the_results(scenario):
    sc = scenario
    rx = can.Bus(channel="test-out", interface="virtual")
    can_sink = CanSink(channel="test-out", interface="virtual")
    import socket
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(1.0)
    udp_sink = UdpSink("127.0.0.1", sock.getsockname()[1])
    pipe = make_pipeline(sc, [can_sink, udp_sink])
    t = sc.epoch_gps_s + 6.0
    results = {vid: pipe.handle(payload(sc, vid, 1, t - 0.1), key(vid), truth_state(sc, "ego", t), t)
               for vid in ("t1", "t2")}
    frames = []
    while (m := rx.recv(timeout=0.1)) is not None:
        frames.append(m)
    dec = decode_frames(frames)
    slots = dict(can_sink.out.slots.items())
    for vid, r in results.items():
        d = dec["targets"][slots[vid]]
        assert d["Status"] == 0
        assert d["PosX"] == pytest.approx(r.rel_pos_body_m[0], abs=1e-3)
        assert d["PosY"] == pytest.approx(r.rel_pos_body_m[1], abs=1e-3)
        assert d["Range"] == pytest.approx(r.range_m, abs=1e-3)
        assert d["Bearing"] == pytest.approx(math.degrees(r.bearing_rad), abs=0.01)
        assert d["VelX"] == pytest.approx(r.rel_vel_body_mps[0], abs=0.01)
        assert d["Latency"] == pytest.approx(r.latency_s * 1e3, abs=0.1)
    got = {}
    for _ in results:
        dg = parse_datagram(sock.recv(65536))
        got[dg.targets[0].target_id] = dg.targets[0]
    for vid, r in results.items():
        assert got[vid].status == r.status
        assert np.allclose(got[vid].rel_pos_body_m, r.rel_pos_body_m, atol=1e-6)
        assert got[vid].range_m == pytest.approx(r.range_m, abs=1e-6)
    assert udp_sink.datagrams == 2
    can_sink.close()
    udp_sink.close()
    rx.shutdown()
    sock.close()


def test_can_rate_limit_keeps_status_changes(scenario):
    sc = scenario
    can_sink = CanSink(channel="test-rate", interface="virtual", rate_hz=25.0)
    pipe = make_pipeline(sc, [can_sink])
    t0 = sc.epoch_gps_s + 4.0
    for k in range(12):
        t = t0 + 0.01 * k
        fix = FixStatus.SINGLE if k == 5 else FixStatus.FIXED
        pipe.handle(payload(sc, "t2", k + 1, t - 0.1, fix), key("t2"), truth_state(sc, "ego", t), t)
    # valid at k = 0, 4, 8 (25 Hz), the FIX_INVALID at k = 5 and the VALID right after it (k = 6)
    assert can_sink.frames == 9 * 4 + 2 and can_sink.skipped == 12 - 5
    can_sink.close()


def test_clock_out_of_bound_or_attitude_pending_is_never_valid(scenario):
    """Either vehicle's clock beyond its bound of GNSS time (slave: the message's ``time_ok``;
    master: ``master_time_ok`` from its own clock) gives CLOCK_UNSYNCED, an undetermined attitude
    on either side ATTITUDE_UNCERTAIN; both recover to VALID when the cause goes."""
    import dataclasses
    sc = scenario
    pipe = make_pipeline(sc)
    t0 = sc.epoch_gps_s + 4.0

    def msg_bytes(seq: int, t_s: float, **flags) -> bytes:
        msg = StateMessage.from_nav_state(truth_state(sc, "t2", t_s), FLEET, "t2", seq,
                                          geometry=sc.actors["t2"].geometry, kind=sc.actors["t2"].kind,
                                          t_sent_wall_s=1.0)
        return encode_state(dataclasses.replace(msg, **flags))

    seq = 0
    statuses = []
    for case in ("ok", "slave_clock", "master_clock", "slave_attitude", "master_attitude", "ok"):
        seq += 1
        t = t0 + 0.01 * seq
        master = truth_state(sc, "ego", t)
        pipe.master_time_ok = case != "master_clock"
        if case == "master_attitude":
            master.attitude_ok = False
        flags = {"time_ok": case != "slave_clock", "attitude_ok": case != "slave_attitude"}
        r = pipe.handle(msg_bytes(seq, t - 0.05, **flags), key("t2"), master, t)
        statuses.append(r.status)
    assert statuses == [TargetStatus.VALID, TargetStatus.CLOCK_UNSYNCED, TargetStatus.CLOCK_UNSYNCED,
                        TargetStatus.ATTITUDE_UNCERTAIN, TargetStatus.ATTITUDE_UNCERTAIN, TargetStatus.VALID]
