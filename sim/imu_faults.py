"""IMU faults injected into simulated units, and a multi-unit vehicle to grade.

Faults (applied to one unit's ``ImuData``; default magnitudes):

- ``gyro_bias_step``: +0.5 deg/s on one gyro axis from ``t_start`` on;
- ``gyro_scale``: gyro scale factor error of 3 % on all axes;
- ``gyro_noise``: gyro white noise x5 (extra noise of sd sqrt(5^2 - 1) sigma, sigma = the unit's
  per-sample noise sd);
- ``stuck_axis``: one gyro axis repeats its value at ``t_start`` (a frozen sensor channel);
- ``time_skew``: the unit's time stamps are 10 ms late (t_stamp = t_true + 0.010 s).

The healthy units come from ``sim.sensors.simulate_imu`` with the ``ImuErrorModel`` preset
(random biases), each mounted with its own declared orientation plus a small undeclared
misalignment, all rigidly attached at the vehicle reference point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xpos.types import ImuData

from .sensors import ImuErrorModel, simulate_imu
from .trajectory import Segment, Trajectory, generate

FAULTS = ("gyro_bias_step", "gyro_scale", "gyro_noise", "stuck_axis", "time_skew")


@dataclass
class FaultSpec:
    """One fault: kind (one of FAULTS), magnitude in the kind's unit (deg/s, fraction, noise
    factor, -, s), gyro axis (0..2) where it applies, start time relative to the first sample [s]."""
    kind: str
    magnitude: float
    axis: int = 2
    t_start_rel_s: float = 0.0


DEFAULT_MAGNITUDE = {"gyro_bias_step": 0.5, "gyro_scale": 0.03, "gyro_noise": 5.0,
                     "stuck_axis": 0.0, "time_skew": 0.010}


def inject_fault(imu: ImuData, fault: FaultSpec, noise_sd_rps: float = 0.0,
                 rng: np.random.Generator | None = None) -> ImuData:
    """A copy of imu with the fault applied (see module doc). noise_sd_rps: per-sample gyro noise
    sd of the healthy unit, needed by ``gyro_noise``."""
    if fault.kind not in FAULTS:
        raise ValueError(f"unknown fault {fault.kind!r}; choose one of {FAULTS}")
    rng = rng or np.random.default_rng(0)
    t = imu.t_s.copy()
    g = imu.gyro_rps.copy()
    a = imu.acc_mps2.copy()
    after = t >= t[0] + fault.t_start_rel_s
    if fault.kind == "gyro_bias_step":
        g[after, fault.axis] += np.radians(fault.magnitude)
    elif fault.kind == "gyro_scale":
        g[after] *= 1.0 + fault.magnitude
    elif fault.kind == "gyro_noise":
        extra = noise_sd_rps * np.sqrt(max(fault.magnitude ** 2 - 1.0, 0.0))
        g[after] += rng.normal(0.0, extra, (int(after.sum()), 3))
    elif fault.kind == "stuck_axis":
        k0 = int(np.argmax(after))
        g[after, fault.axis] = g[k0, fault.axis]
    elif fault.kind == "time_skew":
        t = t + fault.magnitude
    return ImuData(t_s=t, acc_mps2=a, gyro_rps=g, counter_ms=imu.counter_ms)


def manoeuvring_drive(duration_s: float = 60.0, dt_s: float = 0.01, seed: int = 0) -> Trajectory:
    """A drive that keeps turning and changing grade (so all gyro axes see motion): 5 s static,
    accelerate, then alternating curves with pitch changes of +-3 deg, varying with the seed."""
    rng = np.random.default_rng(seed)
    segs = [Segment(5.0), Segment(4.0, accel_mps2=2.5)]
    t = 9.0
    sign = 1.0
    while t < duration_s:
        d = float(rng.uniform(2.0, 4.0))
        segs.append(Segment(d, accel_mps2=float(rng.uniform(-0.8, 0.8)),
                            yaw_rate_rps=sign * float(rng.uniform(0.15, 0.35)),
                            pitch_rad=float(np.radians(rng.uniform(-3.0, 3.0)))))
        sign = -sign
        t += d
    return generate(segs, dt_s=dt_s, speed0_mps=0.0, smooth_tau_s=0.3, roll_per_lat_acc_rad=0.02)


@dataclass
class SimulatedVehicle:
    """Units to grade: ImuData per unit id, declared mounting (X-Y-Z deg, unit -> body), the
    faulty unit id (or None), the fault, the truth trajectory and per-unit noise sd."""
    units: dict
    mounting_xyz_deg: dict
    faulty: str | None
    fault: FaultSpec | None
    trajectory: Trajectory
    noise_sd_rps: dict


def simulate_vehicle(n_units: int = 3, fault_kind: str | None = None, seed: int = 0,
                     duration_s: float = 60.0, rate_hz: float = 100.0, grade: str = "automotive",
                     trajectory: Trajectory | None = None,
                     misalignment_sd_deg: float = 0.5) -> SimulatedVehicle:
    """n_units IMUs on one vehicle; with fault_kind one of them (chosen by the seed) is faulty.

    Mounting angles are multiples of 90 deg about z (declared); each unit has an undeclared
    misalignment of misalignment_sd_deg (1-sigma per axis). Faults start between 30 % and 60 %
    of the run (time skew and scale apply from the start).
    """
    rng = np.random.default_rng(seed)
    traj = trajectory or manoeuvring_drive(duration_s, 1.0 / rate_hz, seed)
    ids = [f"imu{k + 1}" for k in range(n_units)]
    units, mounting, noise = {}, {}, {}
    faulty = ids[int(rng.integers(n_units))] if fault_kind else None
    fault = None
    for k, uid in enumerate(ids):
        model = ImuErrorModel.preset(grade, rng)
        model.misalignment_rad = np.radians(rng.normal(0.0, misalignment_sd_deg, 3))
        yaw_deg = 90.0 * k
        mounting[uid] = np.array([0.0, 0.0, yaw_deg])
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        C_body_imu = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        imu = simulate_imu(traj, model, rate_hz=rate_hz, rng=rng, imu_to_body=C_body_imu)
        noise[uid] = model.gyro_noise_rps_rthz * np.sqrt(rate_hz)
        if uid == faulty:
            dur = float(traj.t_s[-1] - traj.t_s[0])
            start = 0.0 if fault_kind in ("time_skew", "gyro_scale") else float(rng.uniform(0.3, 0.6)) * dur
            fault = FaultSpec(fault_kind, DEFAULT_MAGNITUDE[fault_kind], int(rng.integers(3)), start)
            imu = inject_fault(imu, fault, noise[uid], rng)
        units[uid] = imu
    return SimulatedVehicle(units, mounting, faulty, fault, traj, noise)
