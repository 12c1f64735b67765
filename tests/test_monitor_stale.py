"""The monitor never shows stale data as live (issue 29 item 1), says why a row is not VALID as an
instruction (issue 27 item 4), and formats its master line and waiting screen (issue 29 item 8)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bench.fake_master import result
from v2xpos.monitor import table
from v2xpos.monitor.state import MonitorState
from v2xpos.types import FilterReason, FixStatus
from v2xpos.wire import FixSide, TargetStatus, encode_relative_body

STATUS = {"master_id": "ego", "master_fix": int(FixStatus.FIXED), "phase": "run", "timeout_s": 0.2,
          "status_period_s": 0.5, "t_rel_s": 123.4, "e2e_ms_p99": 12.5, "pipeline_ms_p99": 1.25, "targets": {}}


def _state(results, t_wall: float, status: dict | None = STATUS) -> MonitorState:
    st = MonitorState()
    if status is not None:
        st.on_status(dict(status), t_wall)
    for r in results:
        st.on_relative(encode_relative_body(r), r.target_id, t_wall)
    return st


def test_a_row_older_than_the_timeout_is_stale_not_its_last_status():
    st = _state([result(1, TargetStatus.VALID, 1, 1e9)], 100.0)
    row = st.refresh(100.05)["rows"][0]
    assert row["status"] == "valid" and row["x_m"] is not None
    assert row["age_ms"] == pytest.approx(100.0 + 50.0)         # the master's 100 ms + 50 ms at the monitor
    st.on_status(dict(STATUS), 100.3)                          # the master still talks, but not about t01
    row = st.refresh(100.35)["rows"][0]
    assert row["status"] == "stale" and row["last_status"] == "valid"
    assert row["x_m"] is None and row["range_m"] is None       # no position drawn as if it were current
    assert row["reason"].startswith("no data for 0.4 s") and "VALID" in row["reason"]
    assert (row["last_x_m"], row["last_y_m"]) == pytest.approx((16.0, 0.0))    # drawn dashed where last seen
    assert table.row_line(row).split()[2] == "STALE"


def test_a_master_whose_liveliness_token_went_is_gone_and_every_row_stale():
    st = _state([result(i, TargetStatus.VALID, 1, 1e9) for i in range(3)], 100.0)
    st.on_alive("master", "ego", True, 99.0)
    assert st.refresh(100.05)["master"]["state"] == "live"
    st.on_alive("master", "ego", False, 100.06)
    snap = st.refresh(100.07)                                   # at once, not after a timeout
    assert snap["master"]["state"] == "gone"
    assert {r["status"] for r in snap["rows"]} == {"stale"}
    assert "GONE" in table.master_line(snap) and "STALE" in table.master_line(snap)
    assert all(r["instruction"].startswith("master gone") for r in snap["rows"])


def test_a_master_whose_status_is_overdue_is_gone():
    st = _state([], 100.0)
    assert st.refresh(101.4)["master"]["state"] == "live"
    assert st.refresh(101.6)["master"]["state"] == "gone"       # three status periods of 0.5 s


@pytest.mark.parametrize("status,side,field,reason,words", [
    (TargetStatus.UNVERIFIED, FixSide.SLAVE, "target_reason", FilterReason.SETUP_UNVERIFIED,
     "target: lever arm unverified: drive a turn"),
    (TargetStatus.UNVERIFIED, FixSide.MASTER, "master_reason", FilterReason.TIME_OFFSET_CONVERGING,
     "master: IMU time offset converging"),
    (TargetStatus.UNVERIFIED, FixSide.SLAVE, "target_reason", FilterReason.RECEIVER_FLOAT, "target: receiver float"),
    (TargetStatus.INCONSISTENT, FixSide.MASTER, "master_reason", FilterReason.TEST_POSITION,
     "master: position test failed")])
def test_every_non_valid_row_says_what_to_do(status, side, field, reason, words):
    r = result(1, TargetStatus.VALID, 1, 1e9)
    r.status, r.reason_side = status, side
    setattr(r, field, int(reason))
    row = _state([r], 100.0).refresh(100.01)["rows"][0]
    assert row["status"] == status.name.lower()
    assert row["instruction"].startswith(words), row["instruction"]
    assert reason.name in row["reason"]
    assert words.split(":")[0] in table.row_line(row)


@pytest.mark.parametrize("x_m,y_m,sd_x_m,sd_y_m,range_sd_m,far", [
    (300.0, 10.0, 0.02, 0.30, 0.02, True),     # 300 m ahead, its s.d. across the line of sight: the heading's
    (370.0, 190.0, 0.06, 0.11, 0.005, True),   # 27 deg off the axis: x and y share the heading's error
    (30.0, 1.0, 0.25, 0.25, 0.25, False),      # circular: the receivers', not the range's
    (-250.0, 5.0, 0.03, 0.28, 0.03, True)])    # behind
def test_sigma_over_its_limit_says_whether_range_is_the_cause(x_m, y_m, sd_x_m, sd_y_m, range_sd_m, far):
    r = result(1, TargetStatus.VALID, 1, 1e9)
    r.status = TargetStatus.SIGMA_EXCEEDED
    r.rel_pos_body_m = np.array([x_m, y_m, 0.0])
    r.rel_pos_sd_m = np.array([sd_x_m, sd_y_m, 0.03])
    r.range_m, r.range_sd_m = math.hypot(x_m, y_m), range_sd_m
    row = _state([r], 100.0).refresh(100.01)["rows"][0]
    assert row["status"] == "sigma_exceeded"
    if far:
        assert row["instruction"].startswith(f"target far ({r.range_m:.0f} m)"), row["instruction"]
    else:
        assert row["instruction"] == "sigma above its limit: wait for RTK fixed"


def test_the_clock_alarm_is_shown_as_such():
    status = dict(STATUS, targets={"t01": {"kind": "vehicle", "status": "timeout", "fix_side": 0,
                                           "clock": {"offset_ms": 201.0, "alarm": True}}})
    r = result(1, TargetStatus.TIMEOUT, 1, 1e9)
    r.latency_s, r.reason_side = 0.22, FixSide.MASTER | FixSide.SLAVE
    snap = _state([r], 100.0, status).refresh(100.01)
    row = snap["rows"][0]
    assert row["clock_alarm"] and "clock: target 201 ms behind master" in row["reason"]
    assert row["instruction"].startswith("clocks disagree")
    assert snap["master"]["clock_alarms"] == ["t01"]
    assert table.render(snap).splitlines()[1].startswith("CLOCK ALARM t01")


def test_master_line_prints_times_and_latencies_of_any_size():
    """`t > s` and `e2e p99 > ms` were printed for t >= 10 s and p99 >= 10 ms (a 1-character field)."""
    line = table.master_line(_state([], 100.0).refresh(100.1))
    assert "t 123.4 s" in line and "e2e p99 12.50 ms" in line and "pipeline p99 1.25 ms" in line
    assert ">" not in line and "LIVE" in line and "status 0.1 s old" in line


def test_nothing_heard_and_a_waiting_master_are_said_not_blank():
    st = MonitorState()
    st.refresh(50.0)
    snap = st.refresh(62.0)
    text = table.waiting_text(snap, "tcp/127.0.0.1:7447", "demo", "egoo")
    assert "waiting for master 'egoo' of fleet 'demo' at tcp/127.0.0.1:7447" in text and "12 s" in text
    assert "--master" in text and "--fleet" in text
    waiting = dict(STATUS, phase="clock", waiting_for=["B"], t_rel_s=None)
    snap = _state([], 100.0, waiting).refresh(100.1)
    assert snap["master"]["state"] == "starting"
    assert "STARTING (phase clock, waiting for B)" in table.master_line(snap)


def test_the_vehicle_panel_shows_each_service_and_a_gone_one():
    from v2xpos.sources.status import status_line
    st = _state([], 100.0)
    doc = {"role": "slave", "id": "t1", "clock": {"synchronised": True, "offset_s": 0.001},
           "streams": {"gnss": {"connected": True, "rate_hz": 10.0}, "imu": {"connected": True, "rate_hz": 100.0}},
           "imu_clock": {"drift_ppm": 12.0}, "corrections": {"age_s": 0.8},
           "filter": {"fix": "FIXED", "heading_determined": True, "consistent": True, "verified": False,
                      "reason": "SETUP_UNVERIFIED", "protection_m": 0.31, "sigma_h_m": 0.012}}
    st.on_vehicle_status(doc, 100.0)
    st.on_alive("vehicle", "t1", True, 99.0)
    v = st.refresh(100.2)["vehicles"][0]
    assert v["state"] == "live" and v["instruction"] == "lever arm unverified: drive a turn"
    line = status_line(doc)
    for words in ("clock ok offset 1 ms", "gnss 10/s", "imu 100/s", "imu drift 12 ppm", "corrections 0.8 s old",
                  "unverified PL 0.31 m", "-> lever arm unverified: drive a turn"):
        assert words in line, (words, line)
    st.on_alive("vehicle", "t1", False, 100.3)
    snap = st.refresh(100.4)
    assert snap["vehicles"][0]["state"] == "gone"
    assert "[GONE" in "\n".join(table.vehicle_lines(snap))
    assert math.isfinite(snap["vehicles"][0]["status_age_s"])
