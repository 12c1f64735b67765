"""Grading building blocks on cases with known answers: Kabsch, Euler X-Y-Z, RMSE/PCC, boxplot
statistics, TLS scale, clock offset, stuck channel, rates from poses, bias stability."""
import numpy as np
import pytest

from v2xpos.quality import unit_rotation
from v2xpos.quality.bias import bias_stability, find_stops, stop_biases
from v2xpos.quality.consistency import (box_stats, longest_constant_run_s, pcc_stats, relative_scale,
                                        sliding_window_metrics, tls_slope)
from v2xpos.quality.rate_check import angular_rates_from_poses, interval_mean_rate, rate_check
from v2xpos.quality.timesync import gyro_norm_offset_s, vector_offset_s
from v2xpos.rotation import exp_so3
from v2xpos.types import ImuData


def _rich_rates(n: int, rate_hz: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n) / rate_hz
    w = np.stack([0.5 * np.sin(2 * np.pi * 0.3 * t + 0.2), 0.3 * np.sin(2 * np.pi * 0.7 * t + 1.0),
                  0.4 * np.sin(2 * np.pi * 0.45 * t + 2.0) + 0.1 * np.sin(2 * np.pi * 1.3 * t)], axis=1)
    return t, w


def test_kabsch_recovers_known_rotation_despite_noise_and_bias():
    rng = np.random.default_rng(1)
    t, w_ref = _rich_rates(3000, 100.0, rng)
    C_true = unit_rotation.mounting_dcm([12.0, -35.0, 100.0])
    # unit-under-test rates: w_ut = C_true^T w_ref + bias + noise  ->  C_ref_ut = C_true
    w_ut = w_ref @ C_true + np.array([0.01, -0.02, 0.005]) + rng.normal(0, 0.002, w_ref.shape)
    C_est = unit_rotation.kabsch_rotation(w_ref, w_ut)
    assert unit_rotation.rotation_angle_deg(C_est.T @ C_true) < 0.05
    np.testing.assert_allclose(unit_rotation.euler_xyz_deg_from_dcm(C_est), [12.0, -35.0, 100.0], atol=0.1)
    assert np.isclose(np.linalg.det(C_est), 1.0)
    assert unit_rotation.kabsch_condition(w_ut) > 0.2


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(200, 3))
    b = a * np.array([1.0, 1.0, -1.0])  # a mirror image: the best proper rotation, not the mirror
    C = unit_rotation.kabsch_rotation(a, b)
    assert np.isclose(np.linalg.det(C), 1.0)


@pytest.mark.parametrize("angles", [[0, 0, 0], [10, 20, 30], [-170, 45, 90], [5, -89, -60]])
def test_euler_xyz_roundtrip(angles):
    C = unit_rotation.mounting_dcm(angles)
    np.testing.assert_allclose(unit_rotation.mounting_dcm(unit_rotation.euler_xyz_deg_from_dcm(C)), C, atol=1e-9)


def test_declared_mounting_gives_relative_rotation():
    C_b_ref = unit_rotation.mounting_dcm([0, 0, 90])
    C_b_ut = unit_rotation.mounting_dcm([180, 0, 0])
    C_ref_ut = unit_rotation.relative_from_mounting(C_b_ref, C_b_ut)
    v_ut = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(C_b_ref @ (C_ref_ut @ v_ut), C_b_ut @ v_ut)


def test_window_rmse_pcc_on_known_signals():
    t = np.arange(1000) / 100.0
    x = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * 2 * t), np.sin(2 * np.pi * 3 * t)], axis=1)
    y = x.copy()
    y[:, 0] += 0.3               # constant offset: RMSE 0.3, PCC 1
    y[:, 1] = -x[:, 1]           # inverted: PCC -1, RMSE 2 * rms(cos) = sqrt(2)
    y[:, 2] = 2.0 * x[:, 2]      # scaled: PCC 1, RMSE = rms(sin) = 1/sqrt(2)
    w = sliding_window_metrics(t, x, y, window_n=100, step_n=50)
    assert w.rmse.shape == (19, 3)
    np.testing.assert_allclose(w.rmse[:, 0], 0.3, atol=1e-12)
    np.testing.assert_allclose(w.rmse[:, 1], np.sqrt(2.0), atol=1e-6)
    np.testing.assert_allclose(w.rmse[:, 2], 1 / np.sqrt(2.0), atol=1e-6)
    np.testing.assert_allclose(w.pcc[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(w.pcc[:, 1], -1.0, atol=1e-12)
    np.testing.assert_allclose(w.mean_diff[:, 0], 0.3, atol=1e-12)


def test_pcc_of_independent_noise_is_small_and_of_constant_is_zero():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(20000, 3))
    y = rng.normal(size=(20000, 3))
    y[:, 2] = 5.0
    w = sliding_window_metrics(np.arange(20000) * 0.01, x, y, 1000, 1000)
    assert np.all(np.abs(w.pcc[:, :2]) < 0.15)
    assert np.all(w.pcc[:, 2] == 0.0)
    s = pcc_stats(w.pcc)
    assert len(s["covariance"]) == 3 and abs(s["mean"][0]) < 0.05


def test_box_stats_match_tukey_definition():
    v = np.array([1, 2, 3, 4, 5, 6, 7, 8, 9, 100.0])
    s = box_stats(v)
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    assert s["median"] == med and s["lower_quartile"] == q1 and s["upper_quartile"] == q3
    assert s["upper_whisker"] == 9.0          # 100 is an outlier beyond Q3 + 1.5 IQR
    assert s["lower_whisker"] == 1.0
    assert np.isclose(s["mean"], v.mean()) and np.isclose(s["std"], v.std())


def test_tls_scale_is_unbiased_by_noise_in_both_signals():
    rng = np.random.default_rng(4)
    t = np.arange(6000) / 100.0
    x0 = np.sin(2 * np.pi * 0.2 * t)[:, None] * np.ones(3)
    x = x0 + rng.normal(0, 0.05, x0.shape)
    y = 1.03 * x0 + rng.normal(0, 0.05, x0.shape)
    assert abs(tls_slope(x[:, 0], y[:, 0]) - 1.03) < 0.01
    s = relative_scale(x, y, 100.0, 5.0, min_signal_sd=0.1)
    np.testing.assert_allclose(s, 1.03, atol=0.004)
    assert np.all(np.isnan(relative_scale(x * 0.01, y * 0.01, 100.0, 5.0, min_signal_sd=0.1)))


def test_clock_offset_recovered_from_the_data():
    rng = np.random.default_rng(5)
    t, w = _rich_rates(4000, 100.0, rng)
    C = unit_rotation.mounting_dcm([30.0, 10.0, -70.0])
    shift = 0.0123
    # unit b samples the same motion, but its stamps are late by `shift`
    wb = np.stack([np.interp(t - shift, t, w[:, k]) for k in range(3)], axis=1) @ C
    a = ImuData(t, np.zeros_like(w), w + rng.normal(0, 1e-3, w.shape))
    b = ImuData(t, np.zeros_like(w), wb + rng.normal(0, 1e-3, w.shape))
    off, peak = gyro_norm_offset_s(a, b)
    assert abs(off - shift) < 1e-3 and peak > 0.9
    wb_al = unit_rotation.rotate(b.gyro_rps, C)
    fine = vector_offset_s(t, a.gyro_rps, wb_al, max_lag_s=0.05)
    assert abs(fine - shift) < 3e-4


def test_longest_constant_run_finds_a_stuck_channel():
    t = np.arange(1000) * 0.01
    x = np.random.default_rng(6).normal(size=(1000, 3))
    x[300:500, 1] = x[300, 1]
    runs = longest_constant_run_s(t, x)
    assert runs[0] == 0.0 and runs[2] == 0.0
    assert np.isclose(runs[1], 1.99)


def test_rates_from_poses_recover_a_constant_rotation_rate():
    w_true = np.array([0.05, -0.02, 0.3])
    t = np.arange(11) * 0.1
    poses = np.array([np.block([[exp_so3(w_true * tk), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
                      for tk in t])
    t_mid, w = angular_rates_from_poses(t, poses)
    np.testing.assert_allclose(w, np.tile(w_true, (10, 1)), atol=1e-9)
    t_imu = np.arange(0, 1.0001, 0.01)
    g = np.tile(w_true, (len(t_imu), 1))
    np.testing.assert_allclose(interval_mean_rate(t_imu, g, t), np.tile(w_true, (10, 1)), atol=1e-12)
    ok = rate_check(t, poses, t_imu, g)
    bad = rate_check(t, poses, t_imu, g * 1.03)
    assert not ok.anomaly and abs(ok.mean_diff_dps) < 1e-6
    assert bad.anomaly and np.isclose(bad.mean_diff_dps, 0.03 * np.degrees(np.linalg.norm(w_true)), rtol=1e-6)


def _three_stops_with_bias_step(seed: int) -> ImuData:
    """30 s at 100 Hz: stops around 0-8, 12-20 and 24-30 s, turning between them; +0.5 deg/s gyro-x
    bias step at 16 s (between the 2nd and 3rd stop)."""
    t = np.arange(0, 30, 1 / 100.0)
    moving = ((t > 8) & (t < 12)) | ((t > 20) & (t < 24))
    rng = np.random.default_rng(seed)
    g = rng.normal(0, 1e-4, (len(t), 3))
    g[moving, 2] += 0.3
    g[t > 16, 0] += np.radians(0.5)
    f = np.tile([0.0, 0.0, -9.80665], (len(t), 1)) + rng.normal(0, 0.01, (len(t), 3))
    return ImuData(t, f, g)


def test_bias_stability_between_stops():
    imu = _three_stops_with_bias_step(7)
    stops = find_stops(imu)
    assert len(stops) == 3
    st = bias_stability(stop_biases(imu, stops))
    assert st["n_stops"] == 3
    assert abs(st["spread_dps"][0] - 0.5) < 0.01 and st["spread_dps"][1] < 0.01


def test_bias_stability_from_the_ins_calibrator_and_in_the_verdict():
    from v2xpos.quality import grade_units
    from v2xpos.quality.bias import calibrator_stop_biases, unit_bias_stability

    imu = _three_stops_with_bias_step(8)
    t, f, g = imu.t_s, imu.acc_mps2, imu.gyro_rps
    biases, spans = calibrator_stop_biases(imu)
    assert len(biases) == 3 and spans[0][0] < 8
    st = unit_bias_stability(imu)
    assert st["method"].startswith("ins.StaticCalibrator")
    assert abs(st["spread_dps"][0] - 0.5) < 0.01
    steady = ImuData(t, f, g - np.where(t[:, None] > 16, [np.radians(0.5), 0.0, 0.0], 0.0))
    rep = grade_units({"a": imu, "b": steady})
    by_id = {u["id"]: u for u in rep["units"]}
    assert next(c for c in by_id["a"]["checks"] if c["name"] == "bias_stability")["grade"] == "fail"
    assert next(c for c in by_id["b"]["checks"] if c["name"] == "bias_stability")["grade"] == "pass"


def test_quantised_axis_at_rest_is_not_stuck_but_a_frozen_axis_while_turning_is():
    from v2xpos.quality.consistency import turning_mask
    t = np.arange(2000) * 0.01
    g = np.zeros((2000, 3))
    g[1000:, 2] = 0.3                                  # turning in the second half
    g[:, 0] = np.round(np.random.default_rng(9).normal(0, 1e-4, 2000), 3)  # quantised, quiet: repeats
    active = turning_mask(t, g)
    assert not active[:900].any() and active[1100:].all()
    runs = longest_constant_run_s(t, g, active)
    assert runs[0] > 5.0          # x repeats while turning too (it is frozen by the quantisation)
    g[:, 0] += np.random.default_rng(10).normal(0, 1e-2, 2000)
    assert longest_constant_run_s(t, g, active)[0] == 0.0
    assert longest_constant_run_s(t[:1000], g[:1000], active[:1000])[0] == 0.0


def test_units_at_rest_are_not_aligned_or_synced_from_noise():
    from v2xpos.quality import grade_units
    rng = np.random.default_rng(11)
    t = np.arange(0, 30, 0.01)
    units = {f"u{k}": ImuData(t, np.array([0, 0, -9.81]) + rng.normal(0, 0.02, (len(t), 3)),
                              rng.normal(0, 1e-3, (len(t), 3))) for k in range(3)}
    rep = grade_units(units)
    for u in rep["units"]:
        assert u["grade"] == "pass"
        assert u["time_offset_estimated"] is False and u["time_offset_ms"] == 0.0
        if not u["reference"]:
            assert u["relative_rotation"]["source"].startswith("not observable")
