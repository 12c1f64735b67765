"""Sensor error models: IMU (bias, scale, misalignment, noise, bias random walk) and GNSS (fix-dependent
noise, correlated error, latency, lever arm, fix schedule).

IMU model per axis (Groves 2013 eq. 4.16 simplified to diagonal scale):
    w_meas = M (1 + s_g) w_true + b_g + n_g,     f_meas = M (1 + s_a) f_true + b_a + n_a
where M rotates body-frame quantities into the IMU's axes (``imu_to_body`` transposed, then a small
``misalignment_rad`` rotation), noise densities are in unit/sqrt(Hz) (so the per-sample sd is
density * sqrt(rate)), and biases follow a random walk of density ``*_bias_rw``, plus an optional
step at ``bias_step_t_s`` (a bias shift between two stops, as a temperature change makes).
GNSS errors: white noise per fix status plus a first-order Gauss-Markov term (tau
``gm_tau_s``) that models multipath/atmosphere for float and single fixes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2xpos import geo
from v2xpos.rotation import exp_so3
from v2xpos.types import FixStatus, GnssData, ImuData

from .trajectory import Trajectory


@dataclass
class ImuErrorModel:
    """IMU errors in the IMU's own axes. Units: rad/s, m/s^2, fractions, rad/s/sqrt(Hz), m/s^2/sqrt(Hz)."""
    gyro_bias_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_scale: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_noise_rps_rthz: float = 0.0
    accel_noise_mps2_rthz: float = 0.0
    gyro_bias_rw_rps_rts: float = 0.0
    accel_bias_rw_mps2_rts: float = 0.0
    misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_step_t_s: float | None = None        # from this true time on, the biases are larger by ...
    gyro_bias_step_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))      # ... these
    accel_bias_step_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))    # (IMU axes)

    @classmethod
    def preset(cls, grade: str, rng: np.random.Generator | None = None) -> "ImuErrorModel":
        """Typical figures: 'ideal'; 'tactical' (bias 1 deg/h, ARW 0.1 deg/rt-h);
        'automotive' MEMS (bias 0.05 deg/s, ARW 0.3 deg/rt-h); 'consumer' (0.3 deg/s, 1 deg/rt-h). Biases drawn at random with the preset's 1-sigma when rng is given."""
        specs = {
            "ideal": (0.0, 0.0, 0.0, 0.0),
            "tactical": (np.radians(1.0) / 3600, 0.0005 * 9.81, np.radians(0.1) / 60, 50e-6 * 9.81),
            "automotive": (np.radians(0.05), 0.01, np.radians(0.3) / 60, 150e-6 * 9.81),
            "consumer": (np.radians(0.3), 0.05, np.radians(1.0) / 60, 300e-6 * 9.81),
        }
        if grade not in specs:
            raise ValueError(f"unknown IMU grade {grade!r}; choose one of {sorted(specs)}")
        bg, ba, ng, na = specs[grade]
        rng = rng or np.random.default_rng(0)
        return cls(gyro_bias_rps=rng.normal(0, bg, 3) if bg else np.zeros(3),
                   accel_bias_mps2=rng.normal(0, ba, 3) if ba else np.zeros(3),
                   gyro_noise_rps_rthz=ng, accel_noise_mps2_rthz=na)


def simulate_imu(traj: Trajectory, model: ImuErrorModel | None = None, rate_hz: float | None = None,
                 rng: np.random.Generator | None = None, imu_to_body: np.ndarray | None = None,
                 time_offset_s: float = 0.0) -> ImuData:
    """IMU samples from a truth trajectory.

    imu_to_body: nominal DCM with v_body = imu_to_body @ v_imu (identity by default).
    time_offset_s: the stamps written are t_true - time_offset_s, i.e. the true GPS time of a sample
    is t_stamp + time_offset_s (the convention of ``imu_time_offset_s``).
    """
    model = model or ImuErrorModel()
    rng = rng or np.random.default_rng(0)
    if rate_hz is None or abs(1.0 / rate_hz - traj.dt_s) < 1e-9:
        t, w_b, f_b = traj.t_s, traj.w_ib_b_rps, traj.f_b_mps2
    else:
        t = np.arange(traj.t_s[0], traj.t_s[-1], 1.0 / rate_hz)
        s = traj.sample(t)
        w_b, f_b = s["w_ib_b_rps"], s["f_b_mps2"]
    rate = 1.0 / float(np.median(np.diff(t)))
    n = len(t)
    C_ib = (imu_to_body if imu_to_body is not None else np.eye(3)).T
    C_ib = exp_so3(-np.asarray(model.misalignment_rad, float)) @ C_ib
    w_i = w_b @ C_ib.T
    f_i = f_b @ C_ib.T
    bg = model.gyro_bias_rps + np.cumsum(rng.normal(0, model.gyro_bias_rw_rps_rts / np.sqrt(rate), (n, 3)), axis=0)
    ba = model.accel_bias_mps2 + np.cumsum(rng.normal(0, model.accel_bias_rw_mps2_rts / np.sqrt(rate), (n, 3)), axis=0)
    if model.bias_step_t_s is not None:
        after = (t >= model.bias_step_t_s)[:, None]
        bg = bg + after * np.asarray(model.gyro_bias_step_rps, float)
        ba = ba + after * np.asarray(model.accel_bias_step_mps2, float)
    gyro = w_i * (1.0 + model.gyro_scale) + bg + rng.normal(0, model.gyro_noise_rps_rthz * np.sqrt(rate), (n, 3))
    acc = f_i * (1.0 + model.accel_scale) + ba + rng.normal(0, model.accel_noise_mps2_rthz * np.sqrt(rate), (n, 3))
    return ImuData(t_s=t - time_offset_s, acc_mps2=acc, gyro_rps=gyro)


@dataclass
class GnssErrorModel:
    """GNSS receiver model: 1-sigma horizontal/vertical noise per fix status [m], Gauss-Markov share,
    velocity noise [m/s], output rate, latency_s (each solution is tagged latency_s after the instant
    it describes)."""
    rate_hz: float = 10.0
    sd_h_m: dict = field(default_factory=lambda: {FixStatus.FIXED: 0.01, FixStatus.FLOAT: 0.15,
                                                  FixStatus.DGPS: 0.5, FixStatus.SINGLE: 1.5})
    vertical_factor: float = 1.5
    gm_tau_s: float = 30.0
    gm_share: float = 0.5
    vel_sd_mps: float = 0.02
    latency_s: float = 0.0
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))


def simulate_gnss(traj: Trajectory, model: GnssErrorModel | None = None,
                  rng: np.random.Generator | None = None,
                  fix_schedule: list[tuple[float, float, FixStatus]] | None = None) -> GnssData:
    """GNSS antenna solutions at model.rate_hz.

    fix_schedule: (t_start_s, t_end_s, status) intervals relative to the trajectory start; outside
    them the fix is FIXED. Status NONE produces no epoch. With latency_s > 0 the time tag of each
    epoch is t_true + latency_s: the solution describes an instant latency_s earlier than its tag
    (the convention of ``gnss_latency_s``: a tag is valid at t_tag - gnss_latency_s).
    """
    model = model or GnssErrorModel()
    rng = rng or np.random.default_rng(1)
    t = np.arange(traj.t_s[0], traj.t_s[-1], 1.0 / model.rate_hz)
    rel = t - traj.t_s[0]
    fix = np.full(len(t), FixStatus.FIXED, dtype=int)
    for t0, t1, st in fix_schedule or []:
        fix[(rel >= t0) & (rel < t1)] = int(st)
    keep = fix != FixStatus.NONE
    t, fix = t[keep], fix[keep]
    s = traj.sample(t)
    r_ant = s["r_ned_m"] + np.einsum("nij,j->ni", s["C_nb"], np.asarray(model.lever_arm_m, float))
    sd_h = np.array([model.sd_h_m.get(FixStatus(f), 5.0) for f in fix])
    sd = np.stack([sd_h, sd_h, sd_h * model.vertical_factor], axis=1)
    # white + first-order Gauss-Markov (stationary variance gm_share * sd^2)
    white = rng.normal(0, 1, (len(t), 3)) * sd * np.sqrt(1 - model.gm_share)
    gm = np.zeros((len(t), 3))
    phi = np.exp(-1.0 / (model.rate_hz * model.gm_tau_s))
    for k in range(1, len(t)):
        gm[k] = phi * gm[k - 1] + np.sqrt(1 - phi ** 2) * rng.normal(0, 1, 3)
    err = white + gm * sd * np.sqrt(model.gm_share)
    lla = geo.ned_to_lla(r_ant + err, traj.lla0)
    # antenna velocity: v_ant = v + C_nb (w_nb^b x l^b) (Groves 2013 eq. 14.124, Earth rate neglected)
    v_ant = s["v_ned_mps"] + np.einsum("nij,nj->ni", s["C_nb"],
                                       np.cross(s["w_nb_b_rps"], np.asarray(model.lever_arm_m, float)))
    vel = v_ant + rng.normal(0, model.vel_sd_mps, (len(t), 3))
    return GnssData(t_s=t + model.latency_s, lla=lla, fix=fix, sd_ned_m=sd,
                    vel_ned_mps=vel, vel_sd_ned_mps=np.full((len(t), 3), model.vel_sd_mps))
