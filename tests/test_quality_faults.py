"""Simulated faults in one of three units are graded fail; healthy units never fail (gyro
bias step 0.5 deg/s, scale 3 %, noise x5, stuck axis, 10 ms time skew; 20 seeds each)."""
import numpy as np
import pytest

from sim.imu_faults import FAULTS, FaultSpec, inject_fault, simulate_vehicle
from v2xpos.quality import grade_units
from bench.grading import run_fault_sweep
from v2xpos.types import ImuData


@pytest.mark.slow
def test_fault_sweep_20_seeds_every_fault_fails_no_healthy_unit_fails():
    res = run_fault_sweep(seeds=20, progress=False)
    assert res["none"]["healthy_fail"] == 0
    for kind in FAULTS:
        r = res[kind]
        assert r["detected"] == r["runs"] == 20, (kind, r)
        assert r["healthy_fail"] == 0, (kind, r)


def test_clean_vehicle_all_pass_and_report_keys():
    v = simulate_vehicle(3, None, seed=42)
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg)
    assert [u["grade"] for u in rep["units"]] == ["pass"] * 3
    for u in rep["units"]:
        assert set(u["rmse"]) == {"gyro", "accel"} and len(u["rmse"]["gyro"]) == 3
        assert set(u["pcc"]) == {"gyro", "accel"} and len(u["pcc"]["accel"]) == 3
        if not u["reference"]:
            # the declared 90-degree mountings are recovered up to the simulated 0.5 deg misalignment
            assert u["relative_rotation"]["residual_vs_declared_deg"] < 3.0


def test_time_skew_estimate_matches_the_injected_skew():
    v = simulate_vehicle(3, "time_skew", seed=3)
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg, reference="imu1" if v.faulty != "imu1" else "imu2")
    u = next(u for u in rep["units"] if u["id"] == v.faulty)
    assert abs(abs(u["time_offset_ms"]) - 10.0) < 0.5
    assert u["grade"] == "fail"
    assert next(c for c in u["checks"] if c["name"] == "clock_offset")["grade"] == "fail"


def test_two_units_use_absolute_checks_only():
    v = simulate_vehicle(2, "gyro_scale", seed=5)
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg)
    names = {c["name"] for u in rep["units"] for c in u["checks"]}
    assert "gyro_noise" not in names            # no consensus baseline with two units
    # with two units nobody can tell which one is wrong: both see the 3 % relative scale
    assert all(u["grade"] == "fail" for u in rep["units"])


def test_malformed_samples_are_dropped_and_counted_not_fatal():
    v = simulate_vehicle(3, None, seed=1)
    u = v.units["imu2"]
    g = u.gyro_rps.copy()
    g[100:110] = np.nan
    t = u.t_s.copy()
    t[500] = t[499]          # repeated stamp
    v.units["imu2"] = ImuData(t, u.acc_mps2, g)
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg)
    assert rep["dropped_samples"]["imu2"] == 11
    assert all(x["grade"] == "pass" for x in rep["units"])
    with pytest.raises(ValueError, match="imu3"):
        grade_units({**v.units, "imu3": ImuData(t[:5], u.acc_mps2[:5], g[:5])})
    with pytest.raises(ValueError, match="at least two"):
        grade_units({"imu1": v.units["imu1"]})


def test_inject_fault_kinds():
    v = simulate_vehicle(1, None, seed=0)
    imu = v.units["imu1"]
    f = inject_fault(imu, FaultSpec("stuck_axis", 0.0, axis=0, t_start_rel_s=10.0))
    k = np.searchsorted(imu.t_s, imu.t_s[0] + 10.0)
    assert np.all(f.gyro_rps[k:, 0] == f.gyro_rps[k, 0]) and np.all(f.gyro_rps[:, 1] == imu.gyro_rps[:, 1])
    s = inject_fault(imu, FaultSpec("time_skew", 0.01))
    np.testing.assert_allclose(s.t_s - imu.t_s, 0.01, atol=1e-6)
    with pytest.raises(ValueError):
        inject_fault(imu, FaultSpec("melted", 1.0))


@pytest.mark.slow
def test_second_parameter_with_gnss_separates_a_scale_fault():
    from sim.sensors import simulate_gnss
    from v2xpos import geo

    v = simulate_vehicle(3, "gyro_scale", seed=0)
    gn = simulate_gnss(v.trajectory, rng=np.random.default_rng(0))
    fixes = {"t_s": gn.t_s, "r_ned_m": geo.lla_to_ned(gn.lla, v.trajectory.lla0), "sd_m": 0.02,
             "source": "simulated RTK GNSS"}
    rep = grade_units(v.units, mounting_xyz_deg=v.mounting_xyz_deg, fixes=fixes)
    fused = {u["id"]: u["fused_diff"] for u in rep["units"] if "fused_diff" in u}
    assert len(fused) == 2 and rep["reference"] not in fused
    healthy = next(k for k in fused if k != v.faulty)
    assert fused[healthy]["att_deg"]["p90"] < 0.3 and fused[healthy]["pos_m"]["p90"] < 0.05
    assert fused[v.faulty]["att_deg"]["p90"] > 3 * fused[healthy]["att_deg"]["p90"]
    bad = next(u for u in rep["units"] if u["id"] == v.faulty)
    assert next(c for c in bad["checks"] if c["name"] == "fused_attitude")["grade"] == "fail"
    good = next(u for u in rep["units"] if u["id"] == healthy)
    assert all(c["grade"] == "pass" for c in good["checks"])


def test_units_with_different_sample_rates_are_graded_together():
    from sim.imu_faults import manoeuvring_drive
    from sim.sensors import ImuErrorModel, simulate_imu

    traj = manoeuvring_drive(40.0, 0.005, seed=3)
    rng = np.random.default_rng(3)
    units = {name: simulate_imu(traj, ImuErrorModel.preset("automotive", rng), rate_hz=r, rng=rng)
             for name, r in (("fast", 200.0), ("slow", 100.0), ("mid", 125.0))}
    units["mid"] = inject_fault(units["mid"], FaultSpec("time_skew", 0.010))
    rep = grade_units(units)
    by_id = {u["id"]: u for u in rep["units"]}
    assert by_id["fast"]["grade"] == by_id["slow"]["grade"] == "pass"
    assert by_id["mid"]["grade"] == "fail"
    assert abs(rep["rate_hz"]["fast"] - 200.0) < 0.1
