"""Scoring against the truth (``v2xpos.diagnose.truth``): the availability figures of issue 27 on
synthetic tracks whose answers are known by construction."""
from __future__ import annotations

import math

import numpy as np
import pytest

from v2xpos.diagnose.truth import HEADING_CHANGE_DEG, TruthTrack, first_heading_change_s, score_target


def _track(t_s: np.ndarray, speed_mps: np.ndarray, course_rad: np.ndarray) -> TruthTrack:
    vn, ve = speed_mps * np.cos(course_rad), speed_mps * np.sin(course_rad)
    zeros = np.zeros_like(t_s)
    return TruthTrack(t_s, {"vn": vn, "ve": ve, "vd": zeros, "speed_mps": np.hypot(vn, ve), "yaw_deg": zeros})


def _drive(t_s: np.ndarray, start_s: float, turn_s: float, course0_rad: float, rate_rps: float = 0.1) -> TruthTrack:
    """At rest until ``start_s``, then 10 m/s straight on ``course0_rad``; from ``turn_s`` the
    course changes at ``rate_rps``."""
    speed = np.where(t_s >= start_s, 10.0, 0.0)
    # at rest the velocity is zero and its course meaningless: give it a course far from the drive's
    course = np.where(t_s >= start_s, course0_rad + rate_rps * np.clip(t_s - turn_s, 0.0, None), course0_rad + 2.0)
    return _track(t_s, speed, course)


def test_first_heading_change_is_the_course_leaving_the_drive_off_course():
    t = np.arange(0.0, 100.0, 0.01)
    # the course wraps through +-pi: a drive-off towards the south-west turning right
    tr = _drive(t, 10.0, 40.0, math.pi - 0.05, rate_rps=0.1)
    expected = 40.0 + math.radians(HEADING_CHANGE_DEG) / 0.1
    assert first_heading_change_s(tr) == pytest.approx(expected, abs=0.02)
    # a vehicle that never turns, and one that never moves
    assert first_heading_change_s(_drive(t, 10.0, 1e9, 0.3)) is None
    assert first_heading_change_s(_drive(t, 1e9, 1e9, 0.3)) is None


def _rows(t_s: np.ndarray, valid_from_s: float) -> dict:
    n = len(t_s)
    return {"t_gps_s": t_s, "target": np.array(["B"] * n), "status": np.where(t_s >= valid_from_s, "VALID", "UNVERIFIED"),
            "x_m": np.full(n, -10.0), "y_m": np.zeros(n), "sd_x_m": np.full(n, 0.02), "sd_y_m": np.full(n, 0.02)}


def test_share_after_both_turned_bounds_the_never_verified_valid_share():
    t = np.arange(0.0, 100.0, 0.1)
    rel = TruthTrack(t, {"x_m": np.full(len(t), -10.0), "y_m": np.zeros(len(t))})
    master = _drive(t, 10.0, 30.0, 0.2)
    target = _drive(t, 12.0, 35.0, 0.2)     # the later one decides
    s = score_target(_rows(t, 50.0), "B", rel, master, target)
    t_turned = 35.0 + math.radians(HEADING_CHANGE_DEG) / 0.1
    both = t >= 12.0
    assert s["time_to_turn_s"] == pytest.approx(t_turned - 12.0, abs=0.11)
    assert s["moving_after_turn_fraction"] == pytest.approx(np.mean(t[both] >= t_turned), abs=1e-9)
    assert s["moving_valid_fraction"] == pytest.approx(np.mean(t[both] >= 50.0), abs=1e-9)
    assert s["moving_valid_fraction"] < s["moving_after_turn_fraction"]
    # a follower that never turns: no row of the drive is after a heading change
    s = score_target(_rows(t, 50.0), "B", rel, master, _drive(t, 12.0, 1e9, 0.2))
    assert s["moving_after_turn_fraction"] == 0.0 and s["time_to_turn_s"] is None
