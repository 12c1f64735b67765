"""The IMU's Allan deviation at the stops (``tuning.allan_at_stops``) and what a written
``[calibration]`` table makes the filter model from it: the filter's IMU noise must cover the
Allan deviation the recording shows, not only its white part (docs/calibration.md, "IMU noise
in the table")."""
from __future__ import annotations

import numpy as np

from v2xpos.datasets.calibration import CalibrationTable, CalibrationEntry
from v2xpos.diagnose.inject import N_PARAMS
from v2xpos.diagnose.tuning import allan_at_stops, imu_noise_density
from v2xpos.diagnose.writeback import calibration_table
from v2xpos.ins.calibrated import ins_config
from v2xpos.ins.noise import allan_deviation
from v2xpos.types import GnssData, ImuData

RATE_HZ = 100.0


def _standing(seconds: float, white_rps_rthz: float, gm_sd_rps: float, gm_tau_s: float, seed: int = 0):
    """A car standing still: gyro = white noise + a first-order Gauss-Markov bias (the textbook
    model of bias instability, El-Sheimy et al. 2008), accelerometer white; GNSS at 10 Hz, speed 0."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE_HZ)
    dt = 1.0 / RATE_HZ
    t = 1e6 + np.arange(n) * dt
    phi = np.exp(-dt / gm_tau_s)
    drive = rng.normal(0.0, gm_sd_rps * np.sqrt(1 - phi * phi), (n, 3))
    b = np.zeros((n, 3))
    b[0] = rng.normal(0.0, gm_sd_rps, 3)
    for k in range(1, n):
        b[k] = phi * b[k - 1] + drive[k]
    gyro = 1e-3 + b + rng.normal(0.0, white_rps_rthz * np.sqrt(RATE_HZ), (n, 3))
    acc = np.array([0.0, 0.0, -9.81]) + rng.normal(0.0, 1e-3 * np.sqrt(RATE_HZ), (n, 3))
    tg = np.arange(t[0], t[-1], 0.1)
    m = len(tg)
    gnss = GnssData(t_s=tg, lla=np.tile([0.7, 0.2, 100.0], (m, 1)), fix=np.ones(m, int),
                    sd_ned_m=np.full((m, 3), 0.01), vel_ned_mps=rng.normal(0.0, 0.01, (m, 3)),
                    vel_sd_ned_mps=np.full((m, 3), 0.02))
    return ImuData(t_s=t, acc_mps2=acc, gyro_rps=gyro), gnss


def _table(imu, gnss, with_allan: bool = True) -> CalibrationTable:
    g, a = imu_noise_density(imu)
    allan = allan_at_stops(imu, gnss)
    (gc, gr), (ac, ar) = allan.covering("gyro", g), allan.covering("accel", a)
    z = np.zeros(N_PARAMS)
    return calibration_table(z, np.full(N_PARAMS, 0.01), z.astype(bool), np.ones(N_PARAMS, bool),
                             np.full(N_PARAMS, 0.02), 0.02, source="test", date="2026-11-24", software="test",
                             imu_noise=(g, a, len(imu.t_s)), imu_allan=(gc, ac, gr, ar) if with_allan else None)


def test_overlapping_allan_deviation_of_white_noise_falls_as_one_over_sqrt_tau():
    """IEEE 952: white rate noise of density N has sigma(tau) = N / sqrt(tau)."""
    rng = np.random.default_rng(1)
    n = 1e-3
    x = rng.normal(0.0, n * np.sqrt(RATE_HZ), (200_000, 1))
    for m in (1, 10, 100, 1000):
        tau = m / RATE_HZ
        assert abs(allan_deviation(x, 1 / RATE_HZ, m)[0] / (n / np.sqrt(tau)) - 1) < 0.1, m

    # a record shorter than 2 tau has no second difference at that tau: NaN per axis, not an error
    short = allan_deviation(x[:150], 1 / RATE_HZ, 100)
    assert short.shape == (1,) and np.isnan(short).all()


def test_white_sensor_at_long_stops_is_covered_by_its_white_noise():
    """A sensor with white noise only: the Allan-covering density is its white noise (within the
    estimate's scatter), so the table asks for no more than the second differences measure."""
    imu, gnss = _standing(300.0, 1e-4, 0.0, 1.0)
    allan = allan_at_stops(imu, gnss)
    assert allan.stop_time_s > 290
    g, _ = imu_noise_density(imu)
    assert abs(allan.white("gyro") / 1e-4 - 1) < 0.1
    assert np.isnan(allan.covering("gyro", g)[0])       # nothing above the white line
    assert "imu_gyro_allan_rps_rthz" not in _table(imu, gnss).effects
    _b, bound = allan.bias_instability("gyro")
    assert bound      # no flat part: the instability is only bounded


def test_the_written_table_makes_the_filter_cover_the_allan_deviation_at_the_stops():
    """A quiet gyro (white 1e-5 rad/s/sqrt(Hz)) with a bias instability (Gauss-Markov, 5e-4 rad/s,
    3 s): second differences see the white part only, and a filter given it -- even with the
    calibrated-noise margin -- models an Allan deviation far below the recording's for tau of
    seconds, the times an outage integrates. The table's Allan-covering entry makes the filter's
    white noise lie above the measured deviation at every tau the stops resolve."""
    imu, gnss = _standing(240.0, 1e-5, 5e-4, 3.0)
    allan = allan_at_stops(imu, gnss)
    g, _ = imu_noise_density(imu)
    assert g < 3e-5                      # the second differences miss the instability
    ok = (allan.tau_s >= 1.0) & np.isfinite(allan.gyro_adev_rps[:, 0])
    assert ok.sum() >= 3
    measured = np.max(allan.gyro_adev_rps[ok], axis=1)

    def model(table):
        cfg = ins_config("car", np.eye(3), np.zeros(3), 0.02, table)
        return cfg.imu.gyro_noise_rps_rthz / np.sqrt(allan.tau_s[ok])

    white_only = _table(imu, gnss, with_allan=False)
    assert "imu_gyro_allan_rps_rthz" not in white_only.effects
    assert np.any(model(white_only) < measured)          # white noise x margin: too small
    table = _table(imu, gnss)
    e = table.effects["imu_gyro_allan_rps_rthz"]
    assert e.value > 10 * g and 0 < e.sd < e.value
    assert np.all(model(table) >= measured), (model(table), measured)
    # the table round-trips through TOML with the new entries
    from v2xpos.datasets.calibration import parse_calibration
    import tomllib
    back = parse_calibration(tomllib.loads(table.to_toml())["calibration"], "test")
    assert back.effects["imu_gyro_allan_rps_rthz"].value == e.value
