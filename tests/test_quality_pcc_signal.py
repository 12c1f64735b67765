"""The correlation checks count only windows where the motion stands out of the noise
(``consistency.WindowSeries.signal``, docs/quality.md §3): a drive with one short turn in a minute
is graded on that turn, not on the noise of the straight road; a unit whose axis is noise is still
found, because its quieter partner decides which windows count."""
import numpy as np

from v2xpos.quality.grader import grade_units
from v2xpos.types import ImuData

RATE_HZ = 100.0
DURATION_S = 60.0


def _drive(seed: int, garbage_z_dps: float | None = None) -> dict[str, ImuData]:
    """Two co-mounted units, 60 s straight with one 4-s turn of 20 deg/s peak; noise 0.1 deg/s and
    0.02 m/s^2 per sample."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION_S, 1.0 / RATE_HZ)
    yaw_rate = np.radians(20.0) * np.exp(-0.5 * ((t - 30.0) / 1.0) ** 2)
    gyro = np.zeros((len(t), 3))
    gyro[:, 2] = yaw_rate
    acc = np.zeros((len(t), 3))
    acc[:, 1] = 10.0 * yaw_rate                       # centripetal at 10 m/s
    acc[:, 2] = -9.81
    units = {}
    for uid in ("imu1", "imu2"):
        g = gyro + rng.normal(0.0, np.radians(0.1), gyro.shape)
        a = acc + rng.normal(0.0, 0.02, acc.shape)
        if uid == "imu2" and garbage_z_dps is not None:
            g[:, 2] = rng.normal(0.0, np.radians(garbage_z_dps), len(t))
        units[uid] = ImuData(t_s=t + 1e9, acc_mps2=a, gyro_rps=g)
    return units


def _pcc_check(rep: dict, uid: str) -> dict:
    unit = next(u for u in rep["units"] if u["id"] == uid)
    return next(c for c in unit["checks"] if c["name"] == "gyro_pcc")


def test_one_turn_in_a_minute_grades_healthy_units_on_the_turn():
    mounting = {"imu1": [0.0, 0.0, 0.0], "imu2": [0.0, 0.0, 0.0]}
    for seed in range(3):
        rep = grade_units(_drive(seed), mounting_xyz_deg=mounting, bias_stops=False)
        for u in rep["units"]:
            c = _pcc_check(rep, u["id"])
            assert c["value"] > 0.9 and c["grade"] == "pass", (seed, u["id"], c)
            # the turn's windows, not the minute's: a few windows on z, none on the quiet axes
            n_z = u["pcc_signal_windows"]["gyro"][2]
            assert 4 <= n_z <= 20, u["pcc_signal_windows"]
            assert u["pcc"]["gyro"][0] is None and u["pcc"]["gyro"][1] is None
        # over every window the median correlation is the noise's, ~0: what was graded before
        p = rep["_comparison"].pair("imu1", "imu2")
        assert abs(float(np.median(p.gyro.pcc[:, 2]))) < 0.3


def test_an_axis_of_noise_is_still_found():
    """imu2's z gyro outputs noise of 5 deg/s: the difference's noise is large, but imu1 (quieter)
    decides which windows count, and there imu2 does not correlate."""
    mounting = {"imu1": [0.0, 0.0, 0.0], "imu2": [0.0, 0.0, 0.0]}
    rep = grade_units(_drive(7, garbage_z_dps=5.0), mounting_xyz_deg=mounting, bias_stops=False)
    c = _pcc_check(rep, "imu2")
    assert c["grade"] == "fail" and c["value"] < 0.5, c


def test_a_stuck_axis_does_not_decide_and_a_noiseless_unit_counts_only_its_motion():
    """A z gyro that outputs a constant has no noise: its partner's motion decides, and there it
    does not correlate. Two noiseless units (an ideal simulation) are graded on their motion, not
    on the windows at rest where neither varies."""
    mounting = {"imu1": [0.0, 0.0, 0.0], "imu2": [0.0, 0.0, 0.0]}
    units = _drive(3)
    stuck = units["imu2"].gyro_rps.copy()
    stuck[:, 2] = 0.01
    units["imu2"] = ImuData(t_s=units["imu2"].t_s, acc_mps2=units["imu2"].acc_mps2, gyro_rps=stuck)
    rep = grade_units(units, mounting_xyz_deg=mounting, bias_stops=False)
    assert _pcc_check(rep, "imu2")["grade"] == "fail"
    t = units["imu1"].t_s
    gyro = np.zeros((len(t), 3))
    gyro[:, 2] = np.radians(20.0) * np.exp(-0.5 * ((t - t[0] - 30.0) / 1.0) ** 2)
    acc = np.tile([0.0, 0.0, -9.81], (len(t), 1))
    acc[:, 1] = 10.0 * gyro[:, 2]
    ideal = {u: ImuData(t_s=t, acc_mps2=acc, gyro_rps=gyro) for u in ("imu1", "imu2")}
    rep = grade_units(ideal, mounting_xyz_deg=mounting, bias_stops=False)
    for u in ("imu1", "imu2"):
        c = _pcc_check(rep, u)
        assert c["grade"] == "pass" and c["value"] > 0.99, c
