"""The master's validity rule (issue 15 item 1, docs/integrity.md): a computed result is VALID only
with both attitudes determined, both clocks on GNSS time, both filters consistent and verified, and
the predicted sigma within the configured limits; otherwise the status says why."""
from __future__ import annotations

import math

import numpy as np
import pytest

from master.pipeline import MasterPipeline, PipelineConfig
from v2xpos.types import FilterReason, FixStatus, NavState
from v2xpos.wire import FixSide, StateMessage, TargetStatus, decode_state, encode_state, reason_text

FLEET = "demo"
LAT, LON = math.radians(48.0), math.radians(11.0)


def _nav(t_s: float, north_m: float = 0.0, pos_sd_m: float = 0.01, yaw_sd_rad: float = 1e-3, **flags) -> NavState:
    lla = np.array([LAT + north_m / 6.37e6, LON, 500.0])
    return NavState(t_s=t_s, lla=lla, v_ned_mps=np.array([10.0, 0.0, 0.0]), acc_body_mps2=np.zeros(3),
                    rate_body_rps=np.zeros(3), rpy_rad=np.zeros(3), pos_sd_m=np.full(3, pos_sd_m),
                    vel_sd_mps=np.full(3, 0.02), att_sd_rad=np.array([1e-3, 1e-3, yaw_sd_rad]),
                    fix=FixStatus.FIXED, **flags)


def _result(master: NavState, target: NavState, **cfg) -> TargetStatus:
    pipe = MasterPipeline(PipelineConfig(fleet=FLEET, master_id="ego", **cfg), clock_wall=lambda: 1.0)
    msg = decode_state(encode_state(StateMessage.from_nav_state(target, FLEET, "B", 1)))
    return pipe.handle_message(msg, master, master.t_s, 1.0)


def test_clean_pair_within_limits_is_valid():
    res = _result(_nav(100.0), _nav(99.98, north_m=-20.0))
    assert res.status == TargetStatus.VALID
    assert 0 < math.hypot(*res.rel_pos_sd_m[:2]) < 0.1


@pytest.mark.parametrize("side", ["master", "target"])
@pytest.mark.parametrize("flags,status", [
    ({"attitude_ok": False, "reason": FilterReason.HEADING_PENDING}, TargetStatus.ATTITUDE_UNCERTAIN),
    ({"consistent": False, "reason": FilterReason.TEST_POSITION}, TargetStatus.INCONSISTENT),
    ({"verified": False, "reason": FilterReason.SETUP_UNVERIFIED}, TargetStatus.UNVERIFIED),
    ({"verified": False, "reason": FilterReason.TIME_OFFSET_CONVERGING}, TargetStatus.UNVERIFIED)])
def test_a_vehicle_flag_makes_the_result_not_valid_and_says_why(side, flags, status):
    """A failed test (INCONSISTENT) and "not yet verified" (UNVERIFIED) are told apart, and the result
    names the vehicle and its filter's reason (results.csv ``reason``, CAN ReasonSide/TargetReason)."""
    master = _nav(100.0, **(flags if side == "master" else {}))
    target = _nav(99.98, north_m=-20.0, **(flags if side == "target" else {}))
    res = _result(master, target)
    assert res.status == status
    assert np.all(np.isfinite(res.rel_pos_body_m))          # the kinematics stay in the result
    assert res.reason_side == (FixSide.MASTER if side == "master" else FixSide.SLAVE)
    assert reason_text(res) == f"{side}:{flags['reason'].name}"


def test_the_protection_level_of_the_pair_is_the_sum_of_both():
    res = _result(_nav(100.0, protection_m=0.05), _nav(99.98, north_m=-20.0, protection_m=0.07))
    assert res.protection_m == pytest.approx(0.12)
    assert math.isnan(_result(_nav(100.0), _nav(99.98, north_m=-20.0, protection_m=0.07)).protection_m)


def test_clocks_that_disagree_are_a_clock_alarm_not_only_late_rows():
    """Two services whose clocks differ by 0.2 s: the master's comparison of the send stamps says so
    (CLOCK_UNSYNCED while the rows are computed; TIMEOUT rows name the clock), not TIMEOUT alone."""
    pipe = MasterPipeline(PipelineConfig(fleet=FLEET, master_id="ego"), clock_wall=lambda: 1.0)
    for k in range(20):
        t = 100.0 + 0.01 * k
        target = StateMessage.from_nav_state(_nav(t - 0.02, north_m=-20.0), FLEET, "B", k + 1)
        target.t_sent_gps_s = t - 0.002 - 0.2          # its clock 0.2 s behind the master's, 2 ms transit
        res = pipe.handle(encode_state(target), None, _nav(t), t, 1.0)
    assert res.status == TargetStatus.CLOCK_UNSYNCED
    assert reason_text(res) == "both:CLOCK"
    clock = pipe.summary()["targets"]["B"]["clock"]
    assert clock["alarm"] and clock["offset_ms"] == pytest.approx(202.0)
    silent = pipe.tick(101.0, 101.0)
    assert silent[0].status == TargetStatus.TIMEOUT and reason_text(silent[0]) == "both:CLOCK"


def test_clocks_that_agree_raise_no_alarm():
    pipe = MasterPipeline(PipelineConfig(fleet=FLEET, master_id="ego"), clock_wall=lambda: 1.0)
    for k in range(20):
        t = 100.0 + 0.01 * k
        target = StateMessage.from_nav_state(_nav(t - 0.02, north_m=-20.0), FLEET, "B", k + 1)
        target.t_sent_gps_s = t - 0.002
        res = pipe.handle(encode_state(target), None, _nav(t), t, 1.0)
    assert res.status == TargetStatus.VALID and reason_text(res) == ""
    assert not pipe.summary()["targets"]["B"]["clock"]["alarm"]


def test_consistency_requirement_can_be_switched_off():
    res = _result(_nav(100.0, verified=False), _nav(99.98, north_m=-20.0), require_consistency=False)
    assert res.status == TargetStatus.VALID


def test_predicted_sigma_beyond_the_configured_limits_is_sigma_exceeded():
    # a float target (0.08 m per axis): sigma_h = hypot of both vehicles' sds > 0.10 m
    assert _result(_nav(100.0), _nav(99.98, north_m=-20.0, pos_sd_m=0.08)).status == TargetStatus.SIGMA_EXCEEDED
    assert _result(_nav(100.0), _nav(99.98, north_m=-20.0, pos_sd_m=0.08),
                   max_sigma_h_m=0.2).status == TargetStatus.VALID
    # relative yaw: 1 deg of target yaw sd against a 0.5 deg limit
    res = _result(_nav(100.0), _nav(99.98, north_m=-20.0, yaw_sd_rad=math.radians(1.0)), max_sigma_yaw_deg=0.5)
    assert res.status == TargetStatus.SIGMA_EXCEEDED
    # the master's yaw sd moves the target sideways by range x yaw sd: 20 m x 0.5 deg = 0.17 m
    assert _result(_nav(100.0, yaw_sd_rad=math.radians(0.5)), _nav(99.98, north_m=-20.0)).status \
        == TargetStatus.SIGMA_EXCEEDED


def test_the_yaw_limit_applies_to_vehicle_targets_only():
    target = _nav(99.98, north_m=-20.0, yaw_sd_rad=math.radians(5.0))
    pipe = MasterPipeline(PipelineConfig(fleet=FLEET, master_id="ego"), clock_wall=lambda: 1.0)
    for kind, status in (("vehicle", TargetStatus.SIGMA_EXCEEDED), ("pedestrian", TargetStatus.VALID)):
        msg = decode_state(encode_state(StateMessage.from_nav_state(target, FLEET, kind[0] + "1", 1, kind=kind)))
        assert pipe.handle_message(msg, _nav(100.0), 100.0, 1.0).status == status
