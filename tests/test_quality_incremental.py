"""Incremental grading API (VehicleGrader) used by the master: samples in chunks as they arrive,
bounded history, same verdict as the batch grader, malformed samples rejected and counted."""
import numpy as np

from sim.imu_faults import simulate_vehicle
from v2xpos.quality import VehicleGrader, grade_units


def test_incremental_grades_match_batch_and_flag_the_faulty_unit():
    v = simulate_vehicle(3, "gyro_noise", seed=4, duration_s=60.0)
    g = VehicleGrader(list(v.units), history_s=120.0, min_history_s=10.0,
                      mounting_xyz_deg=v.mounting_xyz_deg)
    first = None
    n = len(v.units["imu1"].t_s)
    for k0 in range(0, n, 50):                     # 0.5 s chunks, units interleaved
        for uid, imu in v.units.items():
            sl = slice(k0, k0 + 50)
            g.add(uid, imu.t_s[sl], imu.gyro_rps[sl], imu.acc_mps2[sl])
        if first is None:
            first = g.grades()
    assert first["status"] == "collecting" and first["units"]["imu1"] is None
    res = g.grades(force=True)
    batch = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg)
    assert res["status"] == "graded"
    assert res["units"] == {u["id"]: u["grade"] for u in batch["units"]}
    assert res["units"][v.faulty] == "fail"
    assert sum(gr == "fail" for gr in res["units"].values()) == 1
    assert isinstance(res["report"]["units"][0]["rmse"]["gyro"][0], float)


def test_history_is_bounded_and_bad_samples_are_counted():
    v = simulate_vehicle(2, None, seed=1, duration_s=40.0)
    g = VehicleGrader(list(v.units), history_s=15.0, min_history_s=10.0)
    for uid, imu in v.units.items():
        assert g.add(uid, imu.t_s, imu.gyro_rps, imu.acc_mps2) == len(imu.t_s)
    kept = g._units()["imu1"]
    assert kept.t_s[-1] - kept.t_s[0] <= 15.0 + 1e-6
    imu = v.units["imu1"]
    assert g.add("imu1", imu.t_s[:10], imu.gyro_rps[:10], imu.acc_mps2[:10]) == 0   # not newer
    assert g.add("imu7", [1.0], [[0, 0, 0]], [[0, 0, 9.8]]) == 0                    # unknown unit
    assert g.add("imu1", [imu.t_s[-1] + 1.0], [[np.nan, 0, 0]], [[0, 0, 9.8]]) == 0  # non-finite
    assert g.add("imu1", [imu.t_s[-1] + 1.0], [[0, 0]], [[0, 0, 9.8]]) == 0          # wrong shape
    assert g.add("imu1", ["x"], [[0, 0, 0]], [[0, 0, 9.8]]) == 0                      # not a number
    assert g.rejected_samples == 14
    res = g.grades()
    assert res["status"] == "graded" and set(res["units"]) == {"imu1", "imu2"}
