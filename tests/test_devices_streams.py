"""Live device streams on recorded bytes (no hardware): framing, UBX / NMEA / csv IMU decoding, the
online IMU clock model, transports on pseudo-terminals and TCP, and the host GNSS clock's bound."""
from __future__ import annotations

import datetime
import json
import math
import os
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from pynmeagps import NMEAMessage

from v2xpos import geo, timebase
from v2xpos.datasets.imu_csv import read_imu_csv
from v2xpos.datasets.issues import ParseIssues
from v2xpos.datasets.timetag import read_timetag
from v2xpos.datasets.ubx import read_ubx, scan_frames
from v2xpos.devices.clock_model import OnlineLowerEnvelope
from v2xpos.devices.emulate import Emulator, timetag_chunks
from v2xpos.devices.framing import NMEA, UBX, StreamFramer, fletcher8
from v2xpos.devices.imu_lines import CsvImuDecoder
from v2xpos.devices.nmea import NmeaDecoder
from v2xpos.devices.records import GnssEpoch, HeadingObs, ImuRecord, ReceiverTime
from v2xpos.devices.stream import DeviceStream
from v2xpos.devices.transport import SerialTransport, TcpTransport
from v2xpos.devices.ubx import UbxDecoder
from v2xpos.sources.gnss_clock import HostGnssClock, clock_from_config
from v2xpos.types import FixStatus
from tests.shared_data import SHARED_DATA, needs_shared

WALK = SHARED_DATA / "walk_0827"
UBX_FILE, UBX_TAG = WALK / "gnss_1730.ubx", WALK / "gnss_1730.ubx.tag"
IMU_FILE, IMU_TAG = WALK / "imu_1730.csv", WALK / "imu_1730.csv.tag"
pytestmark = needs_shared(UBX_FILE)


@pytest.fixture(scope="module")
def ubx_chunks():
    return timetag_chunks(UBX_FILE, UBX_TAG)


@pytest.fixture(scope="module")
def recorded_ubx():
    return read_ubx(UBX_FILE, UBX_TAG)


def _frames(chunks) -> list:
    f = StreamFramer(name="walk")
    out = []
    for t, c in zip(*chunks):
        out += f.feed(c, t)
    return out, f


# ------------------------------------------------------------------ framing
def test_emulator_chunks_are_the_file_and_its_arrival_times(ubx_chunks):
    times, chunks = ubx_chunks
    assert b"".join(chunks) == UBX_FILE.read_bytes()
    tag, _ = read_timetag(UBX_TAG)
    assert np.all(np.diff(times) >= 0) and times[0] >= tag.t_s[0] and times[-1] <= tag.t_s[-1]


@pytest.mark.parametrize("max_chunk", [pytest.param(1, marks=pytest.mark.slow), 13, 4096])
def test_framer_finds_every_frame_whatever_the_chunking(max_chunk):
    raw = UBX_FILE.read_bytes()
    ref, _ = scan_frames(raw, ParseIssues("ref"))
    rng = np.random.default_rng(max_chunk)
    f = StreamFramer(name="x")
    got, k = [], 0
    while k < len(raw):
        n = int(rng.integers(1, max_chunk + 1))
        got += f.feed(raw[k:k + n], float(k))
        k += n
    ubx = [g for g in got if g.protocol == UBX]
    assert [(g.end_offset - len(g.raw), g.end_offset) for g in ubx] == [(r.start, r.end) for r in ref]
    whole = StreamFramer(name="whole")
    whole.feed(raw, 0.0)
    assert sum(g.protocol == NMEA for g in got) == whole.frames[NMEA] == read_ubx(UBX_FILE).message_counts["NMEA sentences"]
    assert f.stats()["malformed"] == 0 and f.stats()["skipped_bytes"] == 0
    # the arrival of a frame is that of the chunk holding its last byte
    assert all(g.arrival_s <= g.end_offset - 1 for g in got)


def test_framer_counts_corruption_and_resynchronises():
    raw = bytearray(UBX_FILE.read_bytes()[:200_000])
    ref, _ = scan_frames(bytes(raw), ParseIssues("ref"))
    hit = [ref[i] for i in (5, 50, 120)]
    for fr in hit:                                       # one byte flipped inside three payloads
        raw[fr.start + 8] ^= 0x5A
    f = StreamFramer(name="x")
    got = f.feed(bytes(raw), 0.0)
    starts = {g.end_offset - len(g.raw) for g in got if g.protocol == UBX}
    assert starts == {r.start for r in ref} - {h.start for h in hit}
    assert f.stats()["malformed"] >= 3
    assert "checksum" in " ".join(e["reason"] for e in f.stats()["malformed_examples"])


# ------------------------------------------------------------------ UBX
def test_ubx_decoder_gives_the_recorded_readers_solutions(ubx_chunks, recorded_ubx):
    frames, _ = _frames(ubx_chunks)
    dec = UbxDecoder()
    recs = []
    for fr in frames:
        if fr.protocol == UBX:
            recs += dec.decode(fr.raw, fr.arrival_s, fr.end_offset)
    epochs = [r for r in recs if isinstance(r, GnssEpoch)]
    times = [r for r in recs if isinstance(r, ReceiverTime)]
    g = recorded_ubx.gnss
    assert len(epochs) == len(g) == len(times)
    np.testing.assert_array_equal([e.t_s for e in epochs], g.t_s)
    np.testing.assert_array_equal(np.array([e.lla for e in epochs]), g.lla)
    np.testing.assert_array_equal(np.array([e.sd_ned_m for e in epochs]), g.sd_ned_m)
    np.testing.assert_array_equal(np.array([e.vel_ned_mps for e in epochs]), g.vel_ned_mps)
    np.testing.assert_array_equal([int(e.fix) for e in epochs], g.fix)
    np.testing.assert_allclose([e.arrival_s for e in epochs], recorded_ubx.arrival_s, atol=1e-9)
    assert {e.fix for e in epochs} == {FixStatus.FIXED, FixStatus.FLOAT}
    assert all(t.gps_minus_utc_s == timebase.gps_minus_utc_at_gps(t.t_s) for t in times)
    assert dec.issues.count == 0


def _ubx(cls: int, mid: int, payload: bytes) -> bytes:
    body = bytes([cls, mid]) + struct.pack("<H", len(payload)) + payload
    a, b = fletcher8(body)
    return b"\xb5\x62" + body + bytes([a, b])


def test_esf_meas_and_raw_become_imu_samples_in_si_units():
    def meas(tag, items):
        payload = struct.pack("<IHH", tag, len(items) << 11, 0) + b"".join(
            struct.pack("<I", (v & 0xFFFFFF) | (t << 24)) for v, t in items)
        return _ubx(0x10, 0x02, payload)
    acc = [(round(0.5 * 1024), 16), (-round(1.25 * 1024), 17), (round(9.81 * 1024), 18)]
    gyr = [(round(10.0 * 4096), 14), (-round(2.0 * 4096), 13), (round(0.25 * 4096), 5), (4096 * 30, 12)]
    dec = UbxDecoder(esf_tick_s=1e-3)
    assert dec.decode(meas(5000, acc), 1.0) == []              # gyro not yet in hand
    (rec,) = dec.decode(meas(5000, gyr), 1.01)
    assert isinstance(rec, ImuRecord) and rec.counter_s == pytest.approx(5.0)
    np.testing.assert_allclose(rec.acc_mps2, [0.5, -1.25, 9.81], atol=1e-3)
    np.testing.assert_allclose(np.degrees(rec.gyro_rps), [10.0, -2.0, 0.25], atol=1e-3)
    raw_payload = b"\0" * 4 + b"".join(struct.pack("<II", (v & 0xFFFFFF) | (t << 24), 777) for v, t in acc + gyr)
    (rec2,) = dec.decode(_ubx(0x10, 0x03, raw_payload), 2.0)
    np.testing.assert_allclose(rec2.acc_mps2, rec.acc_mps2)
    assert rec2.counter_s == pytest.approx(0.777)


def test_relposned_heading_from_a_moving_base_pair():
    from pyubx2 import GET, UBXMessage
    msg = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=1, iTOW=345600250, relPosLength=123,
                     _HPrelPosLength=0.45, relPosHeading=123.45, accHeading=0.5, gnssFixOK=1, relPosValid=1,
                     relPosHeadingValid=1, carrSoln=2, isMoving=1)
    dec = UbxDecoder()
    assert dec.decode(msg.serialize(), 1.0) == []                # no week known before a NAV-PVT
    dec._week = 2381
    (h,) = dec.decode(msg.serialize(), 1.0)
    assert isinstance(h, HeadingObs)
    assert math.degrees(h.heading_rad) == pytest.approx(123.45, abs=1e-4)
    assert math.degrees(h.heading_sd_rad) == pytest.approx(0.5, abs=1e-4)
    assert h.baseline_m == pytest.approx(1.2345, abs=1e-6)
    assert h.t_s == pytest.approx(2381 * 604800 + 345600.25)
    bad = UBXMessage("NAV", "NAV-RELPOSNED", GET, version=1, iTOW=345600250, relPosHeading=10.0, gnssFixOK=1,
                     relPosValid=1, relPosHeadingValid=0)
    assert dec.decode(bad.serialize(), 1.0) == []


# ------------------------------------------------------------------ NMEA
def _nmea_with_generated(ubx_chunks, recorded_ubx):
    """The recorded stream's own GGA/RMC sentences plus GST (NAV-PVT accuracies) and HDT (NAV-PVT
    motion heading) sentences generated from the recording with pynmeagps, each after its epoch's
    RMC/GGA, with the arrival time of the NAV-PVT of that epoch."""
    frames, _ = _frames(ubx_chunks)
    g = recorded_ubx.gnss
    out = []
    k = 0
    for fr in frames:
        if fr.protocol != NMEA:
            continue
        out.append((fr.raw, fr.arrival_s))
        if fr.raw[3:6] == b"GGA" and k < len(g):
            utc = timebase.gps_seconds_to_utc(float(g.t_s[k]))
            tod = datetime.time(utc.hour, utc.minute, utc.second, (utc.microsecond // 10000) * 10000)
            sd = g.sd_ned_m[k]
            gst = NMEAMessage("GN", "GST", 0, time=tod, rangeRms=0.01, stdMajor=float(sd[0]), stdMinor=float(sd[1]),
                              orient=0.0, stdLat=round(float(sd[0]), 4), stdLong=round(float(sd[1]), 4),
                              stdAlt=round(float(sd[2]), 4))
            course = math.degrees(math.atan2(g.vel_ned_mps[k][1], g.vel_ned_mps[k][0])) % 360.0
            hdt = NMEAMessage("GN", "HDT", 0, headingT=round(course, 2), headingTu="T")
            out.append((gst.serialize(), fr.arrival_s))
            out.append((hdt.serialize(), fr.arrival_s))
            k += 1
    return out


def test_nmea_epochs_from_recorded_and_generated_sentences(ubx_chunks, recorded_ubx):
    sentences = _nmea_with_generated(ubx_chunks, recorded_ubx)
    f = StreamFramer((NMEA,), "nmea")
    dec = NmeaDecoder()
    recs = []
    for raw, t in sentences:
        for fr in f.feed(raw, t):
            recs += dec.decode(fr.raw, fr.arrival_s, fr.end_offset)
    epochs = [r for r in recs if isinstance(r, GnssEpoch)]
    heads = [r for r in recs if isinstance(r, HeadingObs)]
    g = recorded_ubx.gnss
    assert len(epochs) >= len(g) - 1 and dec.issues.count == 0 and f.stats()["malformed"] == 0
    by_t = {round(t, 2): i for i, t in enumerate(g.t_s)}
    n_cmp = 0
    for e in epochs:
        i = by_t[round(e.t_s, 2)]
        assert abs(e.t_s - g.t_s[i]) < 2e-3                 # UTC + leap seconds = NAV-PVT GPS time
        d = geo.lla_to_ned(e.lla, g.lla[i])
        # NAV-PVT lat/lon are quantised to 1e-7 deg (0.56 cm north), GGA to 1e-7 min
        assert abs(d[0]) < 0.006 and abs(d[1]) < 0.006 and abs(d[2]) < 2e-3   # alt + sep = ellipsoidal h
        assert e.fix == FixStatus(int(g.fix[i]))                  # quality 4/5 = carrSoln fixed/float
        if e.message == "GGA+RMC+GST":
            np.testing.assert_allclose(e.sd_ned_m, g.sd_ned_m[i], atol=6e-5)
            sp = math.hypot(*g.vel_ned_mps[i][:2])
            assert math.hypot(*e.vel_ned_mps[:2]) == pytest.approx(sp, abs=0.002)
            n_cmp += 1
    assert n_cmp >= len(g) - 2
    assert len(heads) >= len(g) - 1 and all(0 <= h.heading_rad < 2 * math.pi for h in heads)


def test_nmea_malformed_sentences_are_counted_not_fatal():
    good = NMEAMessage("GN", "GGA", 0, time=datetime.time(12, 0, 0), lat=40.1, NS="N", lon=-105.2, EW="W",
                       quality=4, numSV=12, HDOP=0.6, alt=1600.0, altUnit="M", sep=-21.0, sepUnit="M",
                       hpnmeamode=1).serialize()
    bad_ck = good[:-4] + b"00\r\n"
    cut = good[:25]
    f = StreamFramer((NMEA,), "nmea")
    dec = NmeaDecoder()
    recs = []
    for raw in (bad_ck, cut, good, b"$GNGGA,x,y*00\r\n",
                NMEAMessage("GN", "GGA", 0, time=datetime.time(12, 0, 1), lat=40.1, NS="N", lon=-105.2, EW="W",
                            quality=1, numSV=8, HDOP=1.0, alt=1600.0, altUnit="M", sep=-21.0,
                            sepUnit="M").serialize()):
        for fr in f.feed(raw, 1e9):
            recs += dec.decode(fr.raw, fr.arrival_s)
    epochs = [r for r in recs if isinstance(r, GnssEpoch)]
    assert [e.fix for e in epochs] == [FixStatus.FIXED, FixStatus.SINGLE]
    assert epochs[1].t_s - epochs[0].t_s == pytest.approx(1.0)
    assert epochs[0].sd_ned_m[0] == pytest.approx(dec.sd_by_fix_m[FixStatus.FIXED])   # no GST: the table
    assert f.stats()["malformed"] + dec.issues.count >= 3


# ------------------------------------------------------------------ IMU csv and the online clock
def test_online_lower_envelope_equals_the_batch_fit():
    rng = np.random.default_rng(5)
    c = np.cumsum(rng.uniform(0.006, 0.008, 5000))
    arrival = 1000.0 + (1 + 30e-6) * c + rng.exponential(0.008, c.size)
    m = OnlineLowerEnvelope(min_span_s=5.0)
    for ci, ai in zip(c, arrival):
        m.add(ci, ai)
    batch = timebase.fit_clock_lower_envelope(c, arrival)
    assert m.model().drift_ppm == pytest.approx(batch.drift_ppm, abs=1e-6)
    assert m.to_gps(c[-1]) == pytest.approx(batch.to_gps(c[-1]), abs=1e-9)
    early = OnlineLowerEnvelope(min_span_s=5.0)
    for ci, ai in zip(c[:100], arrival[:100]):                    # 0.7 s: slope not yet fitted
        early.add(ci, ai)
    assert early.model().drift_ppm == 0.0 and early.to_gps(c[0]) <= arrival[0]


def test_csv_imu_decoder_and_clock_match_the_recorded_reader():
    times, chunks = timetag_chunks(IMU_FILE, IMU_TAG)
    ref = read_imu_csv(IMU_FILE, IMU_TAG)
    st = DeviceStream("imu", "csv_g_dps_ms", None, lambda r: recs.append(r))
    recs: list[ImuRecord] = []
    for t, c in zip(times, chunks):
        st.feed(c, t)
    recs += st.decoder.imu.flush()
    assert len(recs) == len(ref.imu) and st.decoder.imu.issues.count == ref.issues.count - 1   # the cut last line stays in the buffer
    np.testing.assert_allclose([r.counter_s for r in recs], ref.imu.counter_ms * 1e-3)
    np.testing.assert_allclose(np.array([r.acc_mps2 for r in recs]), ref.imu.acc_mps2)
    m = OnlineLowerEnvelope()
    for r in recs:
        m.add(r.counter_s, r.arrival_s)
    assert m.model().drift_ppm == pytest.approx(ref.clock.drift_ppm, abs=1e-6)
    np.testing.assert_allclose(m.to_gps(recs[-1].counter_s), ref.imu.t_s[-1], atol=1e-6)


# ------------------------------------------------------------------ host GNSS clock
class FakeTime:
    def __init__(self, unix_s: float):
        self.t = unix_s

    def __call__(self) -> float:
        return self.t


def test_clock_offset_bound_turns_synchronised_off():
    ft = FakeTime(1.8e9)
    clk = HostGnssClock(max_offset_s=0.02, latency_floor_s=0.025, window_s=5.0, time_fn=ft)
    assert not clk.synchronised()                                  # no receiver time yet
    rng = np.random.default_rng(1)

    def feed(seconds: float, host_offset_s: float) -> None:
        for _ in range(int(seconds * 4)):
            ft.t += 0.25
            now = clk.now_gps_s()
            t_rx = math.floor((now - host_offset_s) * 4) / 4 - 0.25      # receiver epoch before now
            clk.observe(t_rx, t_rx + host_offset_s + 0.025 + rng.exponential(0.02), 18.0, "NAV-PVT")
    feed(10, 0.0)
    assert clk.synchronised() and abs(clk.offset_s()) < 0.01
    feed(10, 0.030)                                                # host clock 30 ms ahead
    assert not clk.synchronised() and clk.offset_s() == pytest.approx(0.030, abs=0.01)
    assert "offset" in clk.status()["reason"]
    feed(10, -0.030)                                               # 30 ms behind: seen at once
    assert not clk.synchronised() and clk.offset_s() < -0.02
    feed(10, 0.0)
    assert clk.synchronised()
    ft.t += 6.0                                                     # receiver silent
    assert not clk.synchronised() and "no receiver time" in clk.status()["reason"]
    feed(2, 0.0)
    clk.observe(clk.now_gps_s() - 0.03, clk.now_gps_s(), 17.0)       # receiver's leap count disagrees
    assert not clk.synchronised() and clk.leap_mismatches == 1


def test_emulated_clock_bounds_the_offset_in_host_seconds():
    """At emulation speed k a host timing error d shows as k d on the emulated GPS time: 40 ms of
    emulated offset is 10 ms of host time at 4x (synchronised), 40 ms at 1x (not)."""
    for speed, ok in ((4.0, True), (1.0, False)):
        ft = FakeTime(1.8e9)
        clk = HostGnssClock(max_offset_s=0.02, window_s=5.0, emulation_speed=speed, time_fn=ft)
        for _ in range(40):
            ft.t += 0.25 / speed
            t_rx = clk.now_gps_s() - 0.040
            clk.observe(t_rx, clk.now_gps_s(), 18.0, "NAV-PVT")
        assert clk.offset_s() == pytest.approx(0.040)
        assert clk.synchronised() is ok, clk.status()["reason"]


def test_clock_on_the_recorded_nav_pvt_arrivals(recorded_ubx):
    """The recorded arrivals of walk_0827 against its receiver time: with a floor of 0 the output
    latency reads as a host offset beyond 20 ms; with the floor at the smallest latency it is 0."""
    lat = recorded_ubx.latency_s
    g = recorded_ubx.gnss
    for floor, ok in ((0.0, False), (float(np.min(lat)), True)):
        ft = FakeTime(0.0)
        clk = HostGnssClock(latency_floor_s=floor, window_s=30.0, time_fn=ft)
        for t, a in zip(g.t_s, recorded_ubx.arrival_s):
            ft.t = float(timebase.gps_seconds_to_unix(a))
            clk.observe(float(t), float(a), 18.0)
        assert clk.synchronised() is ok


def test_clock_config_and_emulation_mapping():
    ft = FakeTime(1.8e9)
    clk = clock_from_config({"host_time_offset_s": -100.0, "emulation_speed": 2.0}, "[source].clock")
    clk.time_fn = ft
    t0 = clk.now_gps_s()
    assert t0 == pytest.approx(2.0 * timebase.unix_to_gps_seconds(1.8e9) - 100.0)
    ft.t += 1.0
    assert clk.now_gps_s() - t0 == pytest.approx(2.0)
    assert clk.wall_of(t0 + 4.0) == pytest.approx(ft.t + 1.0)
    with pytest.raises(ValueError, match="did you mean 'max_offset_s'"):
        clock_from_config({"max_ofset_s": 0.01}, "[source].clock")


# ------------------------------------------------------------------ transports
def test_serial_transport_on_a_pseudo_terminal_records_a_timetag(tmp_path):
    import tty
    m, s = os.openpty()
    tty.setraw(s)
    path = os.ttyname(s)
    os.close(s)
    got = bytearray()
    clk = HostGnssClock()
    tr = SerialTransport(path, 115200, "gnss", clk.host_gps_s, lambda b, t: got.extend(b),
                         record=tmp_path / "rec.ubx").start()
    deadline = time.time() + 5
    while not tr.connected and time.time() < deadline:
        time.sleep(0.01)
    payload = UBX_FILE.read_bytes()[:30000]
    for k in range(0, len(payload), 1000):
        os.write(m, payload[k:k + 1000])
        time.sleep(0.005)
    deadline = time.time() + 5
    while len(got) < len(payload) and time.time() < deadline:
        time.sleep(0.01)
    assert tr.write(b"\xd3\x00\x00abc") == 6                   # corrections go back into the 'receiver'
    time.sleep(0.05)
    assert os.read(m, 100) == b"\xd3\x00\x00abc"
    tr.close()
    os.close(m)
    assert bytes(got) == payload
    assert (tmp_path / "rec.ubx").read_bytes() == payload
    tag, issues = read_timetag(tmp_path / "rec.ubx.tag")
    assert issues.count == 0 and tag.byte_offset[-1] == len(payload)
    assert abs(tag.t_s[-1] - clk.now_gps_s()) < 5.0


def test_emulator_over_tcp_delivers_the_recorded_bytes():
    emu = Emulator(WALK / "dataset.toml", speed=8.0, tcp=True, start_in_s=0.5, duration_s=4.0, only=["imu"])
    got = bytearray()
    addr = emu.devices()["imu"]["tcp"]
    host, port = addr.split(":")
    clk = HostGnssClock(host_time_offset_s=emu.host_time_offset_s, emulation_speed=emu.speed)
    arrivals = []
    tr = TcpTransport(host, int(port), "imu", clk.host_gps_s,
                      lambda b, t: (got.extend(b), arrivals.append((t, len(got))))).start()
    deadline = time.time() + 3
    while not tr.connected and time.time() < deadline:
        time.sleep(0.01)
    emu.run()
    time.sleep(0.3)
    tr.close()
    emu.close()
    times, chunks = timetag_chunks(IMU_FILE, IMU_TAG)
    sent = b"".join(c for t, c in zip(times, chunks) if t <= emu.t_end_rec_s)
    assert bytes(got) == sent and emu.counts()["imu"]["dropped"] == 0
    # arrival stamps on the emulated clock are the recorded arrivals plus a small positive delay
    t_rec = np.interp([n for _, n in arrivals], np.cumsum([len(c) for c in chunks]), times)
    delay = np.array([t for t, _ in arrivals]) - t_rec
    assert np.median(delay) > -0.02 and np.median(delay) < 0.2


def test_emulate_command_prints_devices_and_timing():
    out = subprocess.run([sys.executable, "-m", "v2xpos.cli", "emulate", str(WALK / "dataset.toml"), "--json",
                          "--duration", "0.5", "--start-in", "0.1", "--speed", "4"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout.splitlines()[0])
    assert set(info["devices"]) == {"gnss", "imu"}
    assert info["devices"]["gnss"]["port"].startswith("/dev/")
    assert info["emulation_speed"] == 4.0 and 0.0 < info["latency_floor_s"] < 0.2
    assert json.loads(out.stdout.splitlines()[-1])["done"]
