"""The convoy as separate OS processes on loopback (master with embedded router, two slaves, one
pedestrian, every one running the INS filter on its simulated sensors), evaluated against truth:
accuracy with 100 ms link latency, compensation gain, fix degradation, delay spike, outputs."""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest

from master.grading import FAIL_CONFIRM_REGRADES, FleetGrader
from sim.demo import run_demo

_GRADER = FleetGrader()
DURATION_S = _GRADER.min_history_s + (FAIL_CONFIRM_REGRADES - 1) * _GRADER.regrade_every_s + 5.0
"""The faulty unit is published "fail" at the regrade that confirms it (after ``min_history_s``, then
one regrade every ``regrade_every_s``); 5 s more leave room for slaves that fall behind real time on
a loaded machine (16 s left 1 s: on CI the confirming regrade was not reached, "warn")."""

REQUIRED_TOP = {"vehicles", "duration_s", "targets", "master_pipeline_ms_p50", "master_pipeline_ms_p99",
                "can_frames", "udp_datagrams"}
REQUIRED_TARGET = {"id", "kind", "samples", "valid_fraction", "rel_pos_err_rms_m", "rel_pos_err_p99_m",
                   "rel_vel_err_rms_mps", "range_err_rms_m", "uncompensated_rel_pos_err_rms_m", "latency_ms_p50",
                   "latency_ms_p99", "rejected"}


@pytest.fixture(scope="module")
def report():
    # own temporary directory: pytest's numbered basetemp dirs can be pruned by concurrent sessions
    with tempfile.TemporaryDirectory(prefix="v2xpos_convoy_") as d:
        out = Path(d)
        rep = run_demo(vehicles=3, duration_s=DURATION_S, latency_ms=100.0, jitter_ms=5.0, seed=0, out=out,
                       source="ins", live=False, plots=True)
        rep["_out"] = out
        yield rep


@pytest.mark.slow
def test_report_layout_and_processes(report):
    out = report["_out"]
    assert REQUIRED_TOP <= set(report)
    on_disk = json.loads((out / "report.json").read_text())
    assert REQUIRED_TOP <= set(on_disk) and len(on_disk["targets"]) == 3
    for t in report["targets"]:
        assert REQUIRED_TARGET <= set(t)
    assert all(code == 0 for code in report["exit_codes"].values()), report["exit_codes"]
    assert {t["id"]: t["kind"] for t in report["targets"]} == {"t1": "vehicle", "t2": "vehicle", "p1": "pedestrian"}
    assert report["vehicles"] == 3
    for png in ("rel_pos_error.png", "range.png", "latency_hist.png", "status.png"):
        assert (out / png).stat().st_size > 1000
    assert report["can_frames"] > 1000 and report["udp_datagrams"] > 1000
    assert report["rejected"] == {}
    grades = report["imu_grades"]               # live IMU grading: faulty unit fails, vehicle degraded
    faulty = report["imu_faults_injected"]
    assert report["imu_grades_final"] is True    # the worker's last regrade reached the report
    assert set(faulty) == {"t2"} and grades["t2"]["units"][faulty["t2"]["unit"]] == "fail"
    assert all(v == "pass" for u, v in grades["t1"]["units"].items())
    assert report["degraded_vehicles"] == ["t2"] and report["degraded_vehicles_ever"] == ["t2"]
    prov = on_disk["provenance"]                # traceable: software, configs' hashes, seeds, start
    assert prov["command"] == "demo" and prov["seeds"] == {"scenario": 0} and prov["configs_sha256"]
    assert {"demo_arguments", "ego", "t1", "t2", "p1"} <= {c["name"] for c in prov["configs"]}
    summary = json.loads((out / "master_summary.json").read_text())
    assert summary["provenance"]["command"] == "master" and summary["provenance"]["configs"][0]["sha256"]
    fix = {x["id"]: x["fix_schedule_rel_s"] for x in on_disk["targets"]}["t2"]   # named fields, no tuples
    assert fix and set(fix[0]) == {"start_rel_s", "end_rel_s", "fix"}
    scene = report["scene"]                     # V2L / V2X from the GeoJSON the demo wrote
    assert scene["updates"] >= 100
    assert max(scene["lane_lateral_err_rms_m"].values()) < 0.05
    assert max(scene["object_distance_err_rms_m"].values()) < 0.05


@pytest.mark.slow
def test_accuracy_and_compensation_with_100ms_latency(report):
    t = {x["id"]: x for x in report["targets"]}
    t1 = t["t1"]                                # cut-in vehicle, 15 m ahead, RTK fixed throughout
    assert t1["samples"] > 1000
    assert t1["rel_pos_err_rms_m"] <= 0.03
    assert t1["uncompensated_rel_pos_err_rms_m"] >= 10 * t1["rel_pos_err_rms_m"]
    assert t1["range_err_rms_m"] <= 0.03
    assert 95.0 <= t1["latency_ms_p50"] <= 150.0             # 100 ms injected + loopback + scheduling
    t2 = t["t2"]                                # 30 m ahead; float then single in the middle of the run
    assert t2["rel_pos_err_rms_rtk_fixed_m"] <= 0.03
    assert t2["uncompensated_rel_pos_err_rms_m"] >= 10 * t2["rel_pos_err_rms_rtk_fixed_m"]


@pytest.mark.slow
def test_fix_degradation_and_delay_spike_statuses(report):
    t = {x["id"]: x for x in report["targets"]}
    t2 = t["t2"]
    assert t2["status_counts"].get("fix_invalid", 0) >= 100     # 2 s of SINGLE at 100 Hz
    assert t2["valid_fraction"] >= 0.7                            # and valid again afterwards
    t1 = t["t1"]
    assert t1["status_counts"].get("timeout", 0) >= 50           # the 300 ms spike
    assert t1["latency_ms_p99"] > 200.0


@pytest.mark.slow
def test_relative_velocity_and_pedestrian(report):
    t = {x["id"]: x for x in report["targets"]}
    assert t["t1"]["rel_vel_err_rms_mps"] <= 0.1
    p1 = t["p1"]
    assert p1["valid_fraction"] >= 0.95 and p1["rel_pos_err_rms_within_50m_m"] <= 0.05
