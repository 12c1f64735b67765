"""v2xpos monitor: table formatting (units, widths, a 12436 s TTC), worst-first order, status
reasons, the status-JSON fallback, and a live attach to a stand-in master over zenoh (a status
change shown within 0.5 s)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from v2xpos.launch import free_tcp_port
from v2xpos.link import LinkConfig
from v2xpos.monitor import table
from v2xpos.monitor.attach import MasterMonitor
from bench.fake_master import result
from v2xpos.monitor.state import MonitorState, status_reason
from v2xpos.monitor.web import WebServer, parse_host_port
from v2xpos.types import FixStatus
from v2xpos.wire import FixSide, TargetStatus, encode_relative_body

ROOT = Path(__file__).resolve().parents[1]


def test_fit_number_never_widens_a_column():
    assert table.fit_number(12436.0, 6, 1) == " 12436"
    assert table.fit_number(12436.0, 4, 1) == " 12k"
    assert table.fit_number(3.14159, 6, 1) == "   3.1"
    assert table.fit_number(999.96, 6, 1) == "1000.0"
    assert table.fit_number(-123456.0, 6, 1) == " -123k"
    assert table.fit_number(None, 6, 1) == "     -"
    assert table.fit_number(float("nan"), 5, 1) == "    -"
    for x in (0.0, 1e-9, 12436.0, 9.99e12, -9.99e12, 123456789.0):
        for w in (5, 6, 8):
            assert len(table.fit_number(x, w, 2)) == w


def _state_with(results: list, t_wall: float = 100.0) -> MonitorState:
    st = MonitorState()
    for r in results:
        st.on_relative(encode_relative_body(r), r.target_id, t_wall)
    return st


def test_rows_sorted_worst_first_and_table_aligned():
    rs = [result(i, TargetStatus.VALID, i + 1, 1e9) for i in range(64)]
    rs[10].ttc_s = 12436.0
    rs[20] = result(20, TargetStatus.FIX_INVALID, 21, 1e9)
    rs[30] = result(30, TargetStatus.TIMEOUT, 31, 1e9)
    rs[30].latency_s = 0.42
    st = _state_with(rs)
    st.on_status({"master_id": "ego", "master_fix": int(FixStatus.FLOAT), "targets": {},
                  "imu_grades": {"t05": {"status": "graded", "units": {"imu1": "pass", "imu2": "fail"}}},
                  "degraded_vehicles": ["t05"]}, 100.0)
    snap = st.refresh(100.1)
    ids = [r["id"] for r in snap["rows"]]
    assert len(ids) == 64
    assert ids[:3] == ["t30", "t20", "t05"]          # timeout, fix_invalid, degraded VALID
    assert ids[3] == "t00"                            # then the shortest TTC
    by = {r["id"]: r for r in snap["rows"]}
    assert by["t30"]["reason"] == "silent 0.4 s"
    assert by["t20"]["reason"] == "fix: target FLOAT"
    assert by["t05"]["imu"] == "FAIL imu2" and "IMU degraded" in by["t05"]["reason"]
    assert by["t01"]["x_m"] == pytest.approx(16.0) and by["t01"]["sigma_h_m"] == pytest.approx(math.hypot(0.02, 0.02))
    assert by["t01"]["rel_yaw_deg"] == pytest.approx(math.degrees(0.05))
    assert (by["t01"]["master_fix"], by["t01"]["target_fix"]) == ("FIXED", "FIXED")   # from the result
    legacy = result(2, TargetStatus.VALID, 3, 1e9)
    legacy.master_fix = legacy.target_fix = FixStatus.NONE          # a master that sends no fixes
    st2 = _state_with([legacy])
    st2.on_status({"master_id": "ego", "master_fix": int(FixStatus.FLOAT), "targets": {}}, 100.0)
    row = st2.refresh(100.1)["rows"][0]
    assert (row["master_fix"], row["target_fix"]) == ("FLOAT", None)   # the master's from its status
    text = table.render(snap)
    lines = text.splitlines()
    header = lines[1]
    for unit in ("range[m]", "x[m]", "y[m]", "yaw[deg]", "sig[m]", "age[ms]", "TTC[s]", "IMU", "reason", "fix M/T"):
        assert unit in header
    assert len({len(line.rstrip()) <= len(header) for line in lines[1:]}) == 1
    ttc_col = header.index("TTC[s]")
    row10 = next(line for line in lines if line.startswith("t10 "))
    assert row10[ttc_col:ttc_col + 6] == " 12436"
    assert len(row10) == len(header)


def test_reasons_for_every_status():
    assert status_reason("fix_invalid", int(FixSide.MASTER | FixSide.SLAVE), "FLOAT", "SINGLE", 50.0, None,
                         False) == "fix: master FLOAT, target SINGLE"
    assert status_reason("no_data", 0, None, None, None, None, False) == "never heard"
    assert status_reason("future", 0, None, None, -30.0, None, False) == "time ahead 30 ms"
    assert status_reason("sigma_exceeded", 0, None, None, 10.0, 0.456, False) == "sigma 0.46 m > limit"
    for s in ("attitude_uncertain", "clock_unsynced", "inconsistent"):
        assert status_reason(s, 0, None, None, None, None, False)
    assert status_reason("valid", 0, None, None, None, None, True) == "IMU degraded"


def test_new_statuses_and_fixes_shown_when_the_result_carries_them():
    r = result(3, TargetStatus.VALID, 1, 1e9)
    r.status = TargetStatus.ATTITUDE_UNCERTAIN
    r.master_fix, r.target_fix = FixStatus.FIXED, FixStatus.FLOAT
    r.rel_yaw_sd_rad = math.radians(2.0)
    st = MonitorState()
    st.on_result(r, 100.0)   # decoded as a master that encodes them would send it
    row = st.refresh(100.0)["rows"][0]
    assert row["status"] == "attitude_uncertain" and row["reason"] == "heading not determined"
    assert (row["master_fix"], row["target_fix"]) == ("FIXED", "FLOAT")
    assert row["sigma_yaw_deg"] == pytest.approx(2.0)
    assert row["x_m"] == pytest.approx(32.0)          # kinematics shown for a kinematic status


def test_rows_from_status_when_no_results():
    st = MonitorState()
    st.on_status({"master_id": "ego", "master_fix": 5, "targets": {
        "B": {"kind": "vehicle", "status": "valid", "fix_side": 0, "degraded": False,
              "last": {"t_gps_s": 1.0, "latency_ms": 100.0, "range_m": 10.0, "bearing_deg": 90.0, "ttc_s": None}},
        "P": {"kind": "pedestrian", "status": "no_data", "fix_side": 0, "degraded": False, "last": None}}}, 5.0)
    rows = {r["id"]: r for r in st.refresh(5.1)["rows"]}
    assert rows["B"]["source"] == "status" and rows["B"]["y_m"] == pytest.approx(10.0)
    assert abs(rows["B"]["x_m"]) < 1e-9
    assert rows["P"]["reason"] == "never heard"


def test_parse_host_port():
    assert parse_host_port("8080") == ("127.0.0.1", 8080)
    assert parse_host_port(":0") == ("127.0.0.1", 0)
    assert parse_host_port("0.0.0.0:81") == ("0.0.0.0", 81)
    with pytest.raises(ValueError):
        parse_host_port("localhost:http")


@pytest.mark.slow
def test_attach_to_a_master_shows_changes_within_half_a_second():
    """A stand-in master (16 targets at 100 Hz, one target's status flipped every 1.3 s) and the
    monitor attached over zenoh with its page served: every flip reaches the snapshot, the
    table and /api/state within 0.5 s."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    pub = subprocess.Popen([sys.executable, "-m", "bench.fake_master", "--endpoint", endpoint,
                            "--targets", "16", "--duration", "9", "--flip-every", "1.3"],
                           stdout=subprocess.PIPE, text=True, cwd=ROOT)
    seen: list[tuple[float, str]] = []

    def on_snapshot(snap):
        text = table.render(snap)
        for r in snap["rows"]:
            if r["id"] == "t08" and (not seen or seen[-1][1] != r["status"]):
                assert r["status"].upper() in text
                seen.append((time.time(), r["status"]))
    mon = None
    try:
        for _ in range(50):
            try:
                mon = MasterMonitor(LinkConfig(mode="client", connect=[endpoint], connect_timeout_ms=1000),
                                    "demo", None, on_snapshot=on_snapshot).start()
                break
            except Exception:
                time.sleep(0.2)
        assert mon is not None
        web = WebServer(mon.snapshot).start()
        out, _ = pub.communicate(timeout=30)
        with urllib.request.urlopen(web.url + "api/state") as r:
            doc = json.loads(r.read())
        with urllib.request.urlopen(web.url) as r:
            assert b"<canvas" in r.read()
        web.close()
    finally:
        if mon is not None:
            mon.close()
        if pub.poll() is None:
            pub.kill()
    assert mon.master_id == "ego"                      # found by its status
    assert len(doc["rows"]) == 16 and doc["lanes"] and doc["trails"]["t00"]
    flips = [json.loads(line) for line in out.splitlines()]
    assert len(flips) >= 5
    for f in flips[:-1]:
        shown = [t for t, s in seen if s == f["status"] and t >= f["t_wall_s"]]
        assert shown, f
        assert shown[0] - f["t_wall_s"] < 0.5, (f, shown[0] - f["t_wall_s"])


def test_last_seen_position_kept_for_a_silent_target():
    st = _state_with([result(1, TargetStatus.VALID, 1, 1e9)], 10.0)
    st.refresh(10.0)
    gone = result(1, TargetStatus.TIMEOUT, 2, 1e9)
    gone.latency_s = 0.5
    st.on_relative(encode_relative_body(gone), "t01", 10.5)
    row = st.refresh(10.5)["rows"][0]
    assert row["status"] == "timeout" and row["x_m"] is None
    assert (row["last_x_m"], row["last_y_m"]) == pytest.approx((16.0, 0.0))
